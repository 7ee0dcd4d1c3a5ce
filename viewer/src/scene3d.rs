//! The 3D view: keyframe point clouds or a triangle mesh, trajectories, keyframe frusta and
//! loop edges drawn with wgpu inside egui (an `egui_wgpu` paint callback). The geometry lives
//! in GPU buffers (points, segments as a line list, mesh vertices and triangle indices) that
//! are uploaded only when the geometry's versions change; every repaint writes the camera
//! uniform, splats the points with two compute passes (`shaders/splat.wgsl`: one pixel per
//! point, nearest wins; software rasterisers such as lavapipe draw point primitives about ten
//! times slower), resolves them into an offscreen colour + depth target, draws the mesh
//! (flat-shaded triangles) and the lines there with depth test, and copies the target into
//! egui's render pass.

use std::sync::Arc;

use bytemuck::{Pod, Zeroable};
use egui_wgpu::wgpu;
use glam::{DVec3, Mat4, Vec3, Vec4};
use rgbid::geometry::Se3;
use wgpu::util::DeviceExt;

/// WGSL of the 3D view.
pub const SHADER: &str = include_str!("../shaders/scene.wgsl");
/// WGSL of the point splatting (compute) and its resolve pass.
pub const SPLAT_SHADER: &str = include_str!("../shaders/splat.wgsl");
/// Point budget on software adapters (lavapipe): the splat passes take about 25 ms per
/// million points on two cores, so two million keep the 3D view near 50 ms per frame there.
pub const SOFTWARE_POINT_BUDGET: u32 = 2_000_000;
/// Threads per workgroup of the splat kernels (`@workgroup_size` in `splat.wgsl`).
const SPLAT_GROUP: u32 = 256;
/// Format of the offscreen colour target (gamma-encoded like egui's colours).
pub const OFFSCREEN_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba8Unorm;
/// Format of the offscreen depth target.
pub const DEPTH_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Depth32Float;

/// One vertex: world position (metres) and RGBA8 colour.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
pub struct Vertex {
    /// World position.
    pub position: [f32; 3],
    /// Colour, RGBA8 (gamma-encoded).
    pub colour: [u8; 4],
}

impl Vertex {
    /// A vertex at `p` (f64 world point) with colour `c`.
    pub fn new(p: DVec3, c: [u8; 4]) -> Self {
        Vertex {
            position: [p.x as f32, p.y as f32, p.z as f32],
            colour: c,
        }
    }
}

/// A triangle mesh of the 3D view.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct MeshGeometry {
    /// Vertices: world position (metres) and colour.
    pub vertices: Vec<Vertex>,
    /// Triangles as indices into `vertices`.
    pub triangles: Vec<[u32; 3]>,
}

/// Everything the 3D view draws. Points, lines and the mesh have their own versions: the
/// trajectory changes every frame, the point cloud only with new keyframes, and only what
/// changed is uploaded again.
#[derive(Clone, Debug, Default)]
pub struct Geometry {
    /// Increases whenever `points` changes.
    pub points_version: u64,
    /// Points, in an interleaved order (see [`interleave`]) so that any prefix is a uniform
    /// subsample: drawing the first `n` is the level of detail under a point budget.
    pub points: Arc<Vec<Vertex>>,
    /// Increases whenever `lines` changes.
    pub lines_version: u64,
    /// Line segments as vertex pairs.
    pub lines: Vec<Vertex>,
    /// Increases whenever `mesh` changes.
    pub mesh_version: u64,
    /// The surface mesh, when the run has one.
    pub mesh: Option<Arc<MeshGeometry>>,
}

/// Reorders `v` so that every prefix is spread over the whole set: element `k` is
/// `v[(k * stride) mod n]` with a stride near `n / golden ratio` coprime to `n`.
pub fn interleave(v: Vec<Vertex>) -> Vec<Vertex> {
    let n = v.len();
    if n < 3 {
        return v;
    }
    let gcd = |mut a: usize, mut b: usize| {
        while b != 0 {
            (a, b) = (b, a % b);
        }
        a
    };
    let mut stride = ((n as f64) * 0.618_033_988_75) as usize;
    while gcd(stride, n) != 1 {
        stride += 1;
    }
    let mut out = Vec::with_capacity(n);
    let mut i = 0usize;
    for _ in 0..n {
        out.push(v[i]);
        i = (i + stride) % n;
    }
    out
}

impl Geometry {
    /// Adds a polyline through `ps` as segments.
    pub fn add_polyline(&mut self, ps: &[DVec3], colour: [u8; 4]) {
        for w in ps.windows(2) {
            self.lines.push(Vertex::new(w[0], colour));
            self.lines.push(Vertex::new(w[1], colour));
        }
    }

    /// Adds a segment.
    pub fn add_segment(&mut self, a: DVec3, b: DVec3, colour: [u8; 4]) {
        self.lines.push(Vertex::new(a, colour));
        self.lines.push(Vertex::new(b, colour));
    }

    /// Adds a camera frustum (pyramid of depth `size` metres, 4:3 image) at `world_from_camera`.
    pub fn add_frustum(&mut self, world_from_camera: &Se3, size: f64, colour: [u8; 4]) {
        let c = world_from_camera.translation;
        let (hw, hh) = (0.5 * size, 0.375 * size);
        let corners = [
            DVec3::new(-hw, -hh, size),
            DVec3::new(hw, -hh, size),
            DVec3::new(hw, hh, size),
            DVec3::new(-hw, hh, size),
        ]
        .map(|p| world_from_camera.transform_point(p));
        for k in 0..4 {
            self.add_segment(c, corners[k], colour);
            self.add_segment(corners[k], corners[(k + 1) % 4], colour);
        }
    }

    fn mesh_vertices(&self) -> &[Vertex] {
        self.mesh.as_ref().map_or(&[], |m| &m.vertices)
    }

    /// Axis-aligned bounds of all vertices, `None` when empty.
    pub fn bounds(&self) -> Option<(Vec3, Vec3)> {
        let mut it = self
            .points
            .iter()
            .chain(&self.lines)
            .chain(self.mesh_vertices())
            .map(|v| Vec3::from(v.position));
        let first = it.next()?;
        Some(it.fold((first, first), |(lo, hi), p| (lo.min(p), hi.max(p))))
    }

    /// Bounds that ignore stray points: the 1st-99th percentile box of (up to 20000 of) the
    /// points and mesh vertices, joined with the lines' bounds.
    pub fn robust_bounds(&self) -> Option<(Vec3, Vec3)> {
        let n = self.points.len() + self.mesh_vertices().len();
        let step = (n / 20_000).max(1);
        let sample: Vec<Vec3> = self
            .points
            .iter()
            .chain(self.mesh_vertices())
            .step_by(step)
            .map(|v| Vec3::from(v.position))
            .collect();
        let mut lo = Vec3::splat(f32::INFINITY);
        let mut hi = Vec3::splat(f32::NEG_INFINITY);
        if sample.len() >= 10 {
            for axis in 0..3 {
                let mut c: Vec<f32> = sample.iter().map(|p| p[axis]).collect();
                c.sort_by(f32::total_cmp);
                lo[axis] = c[c.len() / 100];
                hi[axis] = c[c.len() - 1 - c.len() / 100];
            }
        } else {
            for p in &sample {
                lo = lo.min(*p);
                hi = hi.max(*p);
            }
        }
        for v in &self.lines {
            lo = lo.min(Vec3::from(v.position));
            hi = hi.max(Vec3::from(v.position));
        }
        lo.is_finite().then_some((lo, hi))
    }
}

/// Orbit camera around a target; the world's "up" is -y (camera frames are y-down).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OrbitCamera {
    /// Point orbited and looked at.
    pub target: Vec3,
    /// Rotation about the up axis, radians.
    pub yaw: f32,
    /// Elevation above the horizontal, radians.
    pub pitch: f32,
    /// Distance eye-target, metres.
    pub distance: f32,
    /// Vertical field of view, radians.
    pub fov_y: f32,
}

impl Default for OrbitCamera {
    fn default() -> Self {
        OrbitCamera {
            target: Vec3::new(0.0, 0.0, 1.5),
            yaw: 0.3,
            pitch: 0.6,
            distance: 5.0,
            fov_y: 50f32.to_radians(),
        }
    }
}

const UP: Vec3 = Vec3::new(0.0, -1.0, 0.0);

impl OrbitCamera {
    /// Eye position.
    pub fn eye(&self) -> Vec3 {
        let (sy, cy) = self.yaw.sin_cos();
        let (sp, cp) = self.pitch.sin_cos();
        self.target + self.distance * Vec3::new(sy * cp, -sp, -cy * cp)
    }

    /// `clip_from_world` for a viewport of aspect `width / height` (wgpu depth 0..1).
    pub fn clip_from_world(&self, aspect: f32) -> Mat4 {
        let near = (self.distance * 1e-3).max(1e-3);
        let far = self.distance * 100.0 + 100.0;
        perspective_rh(self.fov_y, aspect.max(1e-3), near, far)
            * look_at_rh(self.eye(), self.target, UP)
    }

    /// Orbit by a drag of `dx, dy` points.
    pub fn orbit(&mut self, dx: f32, dy: f32) {
        self.yaw -= dx * 0.01;
        self.pitch = (self.pitch + dy * 0.01).clamp(-1.55, 1.55);
    }

    /// Pan by a drag of `dx, dy` points in a view `height` points tall.
    pub fn pan(&mut self, dx: f32, dy: f32, height: f32) {
        let forward = (self.target - self.eye()).normalize_or_zero();
        let right = forward.cross(UP).normalize_or_zero();
        let up = right.cross(forward);
        let scale = 2.0 * self.distance * (0.5 * self.fov_y).tan() / height.max(1.0);
        self.target += (-dx * right + dy * up) * scale;
    }

    /// Zoom by a factor (< 1 moves closer).
    pub fn zoom(&mut self, factor: f32) {
        self.distance = (self.distance * factor).clamp(0.01, 1e4);
    }

    /// Looks at the middle of `bounds` from far enough to see all of it.
    pub fn frame_bounds(&mut self, (lo, hi): (Vec3, Vec3)) {
        self.target = 0.5 * (lo + hi);
        let radius = 0.5 * (hi - lo).length();
        self.distance = (radius / (0.5 * self.fov_y).sin()).max(0.1);
    }
}

/// Right-handed view matrix looking from `eye` at `target` (camera looks down -z).
pub fn look_at_rh(eye: Vec3, target: Vec3, up: Vec3) -> Mat4 {
    let f = (target - eye).normalize_or_zero();
    let s = f.cross(up).normalize_or_zero();
    let u = s.cross(f);
    Mat4::from_cols(
        Vec4::new(s.x, u.x, -f.x, 0.0),
        Vec4::new(s.y, u.y, -f.y, 0.0),
        Vec4::new(s.z, u.z, -f.z, 0.0),
        Vec4::new(-s.dot(eye), -u.dot(eye), f.dot(eye), 1.0),
    )
}

/// Right-handed perspective projection with wgpu's depth range 0..1.
pub fn perspective_rh(fov_y: f32, aspect: f32, near: f32, far: f32) -> Mat4 {
    let h = 1.0 / (0.5 * fov_y).tan();
    let w = h / aspect;
    let r = far / (near - far);
    Mat4::from_cols(
        Vec4::new(w, 0.0, 0.0, 0.0),
        Vec4::new(0.0, h, 0.0, 0.0),
        Vec4::new(0.0, 0.0, r, -1.0),
        Vec4::new(0.0, 0.0, r * near, 0.0),
    )
}

/// GPU side of the 3D view. Lives in egui_wgpu's callback resources.
pub struct SceneRenderer {
    splat_depth_pipeline: wgpu::ComputePipeline,
    splat_colour_pipeline: wgpu::ComputePipeline,
    splat_layout: wgpu::BindGroupLayout,
    resolve_pipeline: wgpu::RenderPipeline,
    resolve_layout: wgpu::BindGroupLayout,
    params_buffer: wgpu::Buffer,
    line_pipeline: wgpu::RenderPipeline,
    mesh_pipeline: wgpu::RenderPipeline,
    blit_pipeline: wgpu::RenderPipeline,
    camera_buffer: wgpu::Buffer,
    camera_group: wgpu::BindGroup,
    blit_layout: wgpu::BindGroupLayout,
    sampler: wgpu::Sampler,
    target: Option<Offscreen>,
    points: Option<(wgpu::Buffer, u32)>,
    lines: Option<(wgpu::Buffer, u32)>,
    /// Mesh vertex buffer, index buffer and index count.
    mesh: Option<(wgpu::Buffer, wgpu::Buffer, u32)>,
    points_version: Option<u64>,
    lines_version: Option<u64>,
    mesh_version: Option<u64>,
    point_budget: u32,
    show_points: bool,
    show_mesh: bool,
}

struct Offscreen {
    size: [u32; 2],
    colour: wgpu::Texture,
    colour_view: wgpu::TextureView,
    depth_view: wgpu::TextureView,
    blit_group: wgpu::BindGroup,
    /// Per pixel: depth key of the nearest point (0 = none), see `splat.wgsl`.
    splat_depth: wgpu::Buffer,
    /// Per pixel: RGBA8 colour of the nearest point.
    splat_colour: wgpu::Buffer,
    resolve_group: wgpu::BindGroup,
}

impl SceneRenderer {
    /// Pipelines for an egui render pass of `target_format` with `msaa_samples` and an
    /// optional depth attachment (`egui_wgpu::RendererOptions`).
    pub fn new(
        device: &wgpu::Device,
        target_format: wgpu::TextureFormat,
        msaa_samples: u32,
        egui_depth_format: Option<wgpu::TextureFormat>,
    ) -> Self {
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("rgbid-viewer scene"),
            source: wgpu::ShaderSource::Wgsl(SHADER.into()),
        });
        let camera_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("scene camera"),
            entries: &[wgpu::BindGroupLayoutEntry {
                binding: 0,
                visibility: wgpu::ShaderStages::VERTEX,
                ty: wgpu::BindingType::Buffer {
                    ty: wgpu::BufferBindingType::Uniform,
                    has_dynamic_offset: false,
                    min_binding_size: None,
                },
                count: None,
            }],
        });
        let blit_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("scene blit"),
            entries: &[
                wgpu::BindGroupLayoutEntry {
                    binding: 0,
                    visibility: wgpu::ShaderStages::FRAGMENT,
                    ty: wgpu::BindingType::Texture {
                        sample_type: wgpu::TextureSampleType::Float { filterable: true },
                        view_dimension: wgpu::TextureViewDimension::D2,
                        multisampled: false,
                    },
                    count: None,
                },
                wgpu::BindGroupLayoutEntry {
                    binding: 1,
                    visibility: wgpu::ShaderStages::FRAGMENT,
                    ty: wgpu::BindingType::Sampler(wgpu::SamplerBindingType::Filtering),
                    count: None,
                },
            ],
        });
        let scene_pl = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("scene"),
            bind_group_layouts: &[Some(&camera_layout)],
            immediate_size: 0,
        });
        let blit_pl = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("scene blit"),
            bind_group_layouts: &[Some(&blit_layout)],
            immediate_size: 0,
        });
        let attributes = wgpu::vertex_attr_array![0 => Float32x3, 1 => Unorm8x4];
        let vertex_layout = wgpu::VertexBufferLayout {
            array_stride: std::mem::size_of::<Vertex>() as u64,
            step_mode: wgpu::VertexStepMode::Vertex,
            attributes: &attributes,
        };
        // Lines (`vs_scene`/`fs_scene`) and mesh triangles (`vs_mesh`/`fs_mesh`: drawn from
        // both sides, as marching-cubes meshes are open surfaces, and shaded in the fragment
        // shader from the screen-space derivatives of the world position).
        let scene_pipeline = |topology, label, (vs, fs): (&str, &str)| {
            device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
                label: Some(label),
                layout: Some(&scene_pl),
                vertex: wgpu::VertexState {
                    module: &module,
                    entry_point: Some(vs),
                    compilation_options: Default::default(),
                    buffers: &[Some(vertex_layout.clone())],
                },
                primitive: wgpu::PrimitiveState {
                    topology,
                    cull_mode: None,
                    ..Default::default()
                },
                depth_stencil: Some(wgpu::DepthStencilState {
                    format: DEPTH_FORMAT,
                    depth_write_enabled: Some(true),
                    depth_compare: Some(wgpu::CompareFunction::Less),
                    stencil: Default::default(),
                    bias: Default::default(),
                }),
                multisample: Default::default(),
                fragment: Some(wgpu::FragmentState {
                    module: &module,
                    entry_point: Some(fs),
                    compilation_options: Default::default(),
                    targets: &[Some(OFFSCREEN_FORMAT.into())],
                }),
                multiview_mask: None,
                cache: None,
            })
        };
        let line_pipeline = scene_pipeline(
            wgpu::PrimitiveTopology::LineList,
            "scene lines",
            ("vs_scene", "fs_scene"),
        );
        let mesh_pipeline = scene_pipeline(
            wgpu::PrimitiveTopology::TriangleList,
            "scene mesh",
            ("vs_mesh", "fs_mesh"),
        );
        let blit_pipeline = device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
            label: Some("scene blit"),
            layout: Some(&blit_pl),
            vertex: wgpu::VertexState {
                module: &module,
                entry_point: Some("vs_blit"),
                compilation_options: Default::default(),
                buffers: &[],
            },
            primitive: Default::default(),
            depth_stencil: egui_depth_format.map(|format| wgpu::DepthStencilState {
                format,
                depth_write_enabled: Some(false),
                depth_compare: Some(wgpu::CompareFunction::Always),
                stencil: Default::default(),
                bias: Default::default(),
            }),
            multisample: wgpu::MultisampleState {
                count: msaa_samples.max(1),
                ..Default::default()
            },
            fragment: Some(wgpu::FragmentState {
                module: &module,
                entry_point: Some(if target_format.is_srgb() {
                    "fs_blit_linear"
                } else {
                    "fs_blit_gamma"
                }),
                compilation_options: Default::default(),
                targets: &[Some(target_format.into())],
            }),
            multiview_mask: None,
            cache: None,
        });
        let splat_module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("rgbid-viewer splat"),
            source: wgpu::ShaderSource::Wgsl(SPLAT_SHADER.into()),
        });
        let entry = |binding, visibility, ty| wgpu::BindGroupLayoutEntry {
            binding,
            visibility,
            ty,
            count: None,
        };
        let uniform = wgpu::BindingType::Buffer {
            ty: wgpu::BufferBindingType::Uniform,
            has_dynamic_offset: false,
            min_binding_size: None,
        };
        let storage = |read_only| wgpu::BindingType::Buffer {
            ty: wgpu::BufferBindingType::Storage { read_only },
            has_dynamic_offset: false,
            min_binding_size: None,
        };
        let compute = wgpu::ShaderStages::COMPUTE;
        let splat_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("scene splat"),
            entries: &[
                entry(0, compute, uniform),
                entry(1, compute, uniform),
                entry(2, compute, storage(true)),
                entry(3, compute, storage(false)),
                entry(4, compute, storage(false)),
            ],
        });
        let fragment = wgpu::ShaderStages::FRAGMENT;
        let resolve_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("scene splat resolve"),
            entries: &[
                entry(0, fragment, uniform),
                entry(1, fragment, storage(true)),
                entry(2, fragment, storage(true)),
            ],
        });
        let splat_pl = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("scene splat"),
            bind_group_layouts: &[Some(&splat_layout)],
            immediate_size: 0,
        });
        let splat_pipeline = |entry_point, label| {
            device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some(label),
                layout: Some(&splat_pl),
                module: &splat_module,
                entry_point: Some(entry_point),
                compilation_options: Default::default(),
                cache: None,
            })
        };
        let splat_depth_pipeline = splat_pipeline("splat_depth", "scene splat depth");
        let splat_colour_pipeline = splat_pipeline("splat_colour", "scene splat colour");
        let resolve_pl = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("scene splat resolve"),
            bind_group_layouts: &[Some(&resolve_layout)],
            immediate_size: 0,
        });
        let resolve_pipeline = device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
            label: Some("scene splat resolve"),
            layout: Some(&resolve_pl),
            vertex: wgpu::VertexState {
                module: &splat_module,
                entry_point: Some("vs_resolve"),
                compilation_options: Default::default(),
                buffers: &[],
            },
            primitive: Default::default(),
            depth_stencil: Some(wgpu::DepthStencilState {
                format: DEPTH_FORMAT,
                depth_write_enabled: Some(true),
                depth_compare: Some(wgpu::CompareFunction::Always),
                stencil: Default::default(),
                bias: Default::default(),
            }),
            multisample: Default::default(),
            fragment: Some(wgpu::FragmentState {
                module: &splat_module,
                entry_point: Some("fs_resolve"),
                compilation_options: Default::default(),
                targets: &[Some(OFFSCREEN_FORMAT.into())],
            }),
            multiview_mask: None,
            cache: None,
        });
        let params_buffer = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("scene splat params"),
            size: 16,
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let camera_buffer = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("scene camera"),
            size: 64,
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let camera_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("scene camera"),
            layout: &camera_layout,
            entries: &[wgpu::BindGroupEntry {
                binding: 0,
                resource: camera_buffer.as_entire_binding(),
            }],
        });
        let sampler = device.create_sampler(&wgpu::SamplerDescriptor {
            label: Some("scene blit"),
            mag_filter: wgpu::FilterMode::Nearest,
            min_filter: wgpu::FilterMode::Nearest,
            ..Default::default()
        });
        SceneRenderer {
            splat_depth_pipeline,
            splat_colour_pipeline,
            splat_layout,
            resolve_pipeline,
            resolve_layout,
            params_buffer,
            line_pipeline,
            mesh_pipeline,
            blit_pipeline,
            camera_buffer,
            camera_group,
            blit_layout,
            sampler,
            target: None,
            points: None,
            lines: None,
            mesh: None,
            points_version: None,
            lines_version: None,
            mesh_version: None,
            point_budget: u32::MAX,
            show_points: true,
            show_mesh: true,
        }
    }

    /// Uploads what changed in `geometry` (by version). Returns whether the points were uploaded.
    pub fn upload(&mut self, device: &wgpu::Device, geometry: &Geometry) -> bool {
        let make = |v: &[Vertex], label| {
            (!v.is_empty()).then(|| {
                (
                    device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                        label: Some(label),
                        contents: bytemuck::cast_slice(v),
                        // Lines are drawn from it, points read by the splat kernels.
                        usage: wgpu::BufferUsages::VERTEX | wgpu::BufferUsages::STORAGE,
                    }),
                    v.len() as u32,
                )
            })
        };
        if self.lines_version != Some(geometry.lines_version) {
            self.lines = make(&geometry.lines, "scene lines");
            self.lines_version = Some(geometry.lines_version);
        }
        if self.mesh_version != Some(geometry.mesh_version) {
            self.mesh = geometry
                .mesh
                .as_ref()
                .filter(|m| !m.vertices.is_empty() && !m.triangles.is_empty())
                .map(|m| {
                    let vertices = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                        label: Some("scene mesh vertices"),
                        contents: bytemuck::cast_slice(&m.vertices),
                        usage: wgpu::BufferUsages::VERTEX,
                    });
                    let indices = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                        label: Some("scene mesh indices"),
                        contents: bytemuck::cast_slice(&m.triangles),
                        usage: wgpu::BufferUsages::INDEX,
                    });
                    (vertices, indices, 3 * m.triangles.len() as u32)
                });
            self.mesh_version = Some(geometry.mesh_version);
        }
        if self.points_version == Some(geometry.points_version) {
            return false;
        }
        self.points = make(&geometry.points, "scene points");
        self.points_version = Some(geometry.points_version);
        true
    }

    /// Most points drawn per frame (a prefix of the interleaved buffer); `u32::MAX` = all.
    pub fn set_point_budget(&mut self, budget: u32) {
        self.point_budget = budget.max(1);
    }

    /// Whether the points and the mesh are drawn (both by default).
    pub fn set_visible(&mut self, points: bool, mesh: bool) {
        self.show_points = points;
        self.show_mesh = mesh;
    }

    fn ensure_target(&mut self, device: &wgpu::Device, size: [u32; 2]) {
        let size = [size[0].clamp(1, 8192), size[1].clamp(1, 8192)];
        if self.target.as_ref().is_some_and(|t| t.size == size) {
            return;
        }
        let extent = wgpu::Extent3d {
            width: size[0],
            height: size[1],
            depth_or_array_layers: 1,
        };
        let texture = |format, usage, label| {
            device.create_texture(&wgpu::TextureDescriptor {
                label: Some(label),
                size: extent,
                mip_level_count: 1,
                sample_count: 1,
                dimension: wgpu::TextureDimension::D2,
                format,
                usage,
                view_formats: &[],
            })
        };
        let colour = texture(
            OFFSCREEN_FORMAT,
            wgpu::TextureUsages::RENDER_ATTACHMENT
                | wgpu::TextureUsages::TEXTURE_BINDING
                | wgpu::TextureUsages::COPY_SRC,
            "scene colour",
        );
        let depth = texture(
            DEPTH_FORMAT,
            wgpu::TextureUsages::RENDER_ATTACHMENT,
            "scene depth",
        );
        let colour_view = colour.create_view(&Default::default());
        let depth_view = depth.create_view(&Default::default());
        let blit_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("scene blit"),
            layout: &self.blit_layout,
            entries: &[
                wgpu::BindGroupEntry {
                    binding: 0,
                    resource: wgpu::BindingResource::TextureView(&colour_view),
                },
                wgpu::BindGroupEntry {
                    binding: 1,
                    resource: wgpu::BindingResource::Sampler(&self.sampler),
                },
            ],
        });
        let pixels = u64::from(size[0]) * u64::from(size[1]);
        let splat_buffer = |label, usage| {
            device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size: 4 * pixels,
                usage: wgpu::BufferUsages::STORAGE | usage,
                mapped_at_creation: false,
            })
        };
        let splat_depth = splat_buffer("scene splat depth", wgpu::BufferUsages::COPY_DST);
        let splat_colour = splat_buffer("scene splat colour", wgpu::BufferUsages::empty());
        let resolve_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("scene splat resolve"),
            layout: &self.resolve_layout,
            entries: &[
                wgpu::BindGroupEntry {
                    binding: 0,
                    resource: self.params_buffer.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 1,
                    resource: splat_depth.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 2,
                    resource: splat_colour.as_entire_binding(),
                },
            ],
        });
        self.target = Some(Offscreen {
            size,
            colour,
            colour_view,
            depth_view,
            blit_group,
            splat_depth,
            splat_colour,
            resolve_group,
        });
    }

    /// Draws the uploaded geometry into the offscreen target of `size` pixels.
    pub fn render(
        &mut self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        encoder: &mut wgpu::CommandEncoder,
        clip_from_world: Mat4,
        size: [u32; 2],
        background: [f32; 3],
    ) {
        self.ensure_target(device, size);
        queue.write_buffer(
            &self.camera_buffer,
            0,
            bytemuck::cast_slice(&clip_from_world.to_cols_array()),
        );
        let Some(target) = &self.target else {
            return;
        };
        let count = self
            .points
            .as_ref()
            .filter(|_| self.show_points)
            .map_or(0, |(_, n)| (*n).min(self.point_budget));
        if let (Some((points, _)), true) = (&self.points, count > 0) {
            let groups = count.div_ceil(SPLAT_GROUP);
            let (gx, gy) = (groups.min(65_535), groups.div_ceil(65_535));
            let params = [target.size[0], target.size[1], count, gx * SPLAT_GROUP];
            queue.write_buffer(&self.params_buffer, 0, bytemuck::cast_slice(&params));
            encoder.clear_buffer(&target.splat_depth, 0, None);
            let group = device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("scene splat"),
                layout: &self.splat_layout,
                entries: &[
                    wgpu::BindGroupEntry {
                        binding: 0,
                        resource: self.camera_buffer.as_entire_binding(),
                    },
                    wgpu::BindGroupEntry {
                        binding: 1,
                        resource: self.params_buffer.as_entire_binding(),
                    },
                    wgpu::BindGroupEntry {
                        binding: 2,
                        resource: points.as_entire_binding(),
                    },
                    wgpu::BindGroupEntry {
                        binding: 3,
                        resource: target.splat_depth.as_entire_binding(),
                    },
                    wgpu::BindGroupEntry {
                        binding: 4,
                        resource: target.splat_colour.as_entire_binding(),
                    },
                ],
            });
            // Two passes: every point's depth is in before the colours are chosen.
            for pipeline in [&self.splat_depth_pipeline, &self.splat_colour_pipeline] {
                let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                    label: Some("scene splat"),
                    timestamp_writes: None,
                });
                pass.set_pipeline(pipeline);
                pass.set_bind_group(0, &group, &[]);
                pass.dispatch_workgroups(gx, gy, 1);
            }
        }
        let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
            label: Some("scene"),
            color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                view: &target.colour_view,
                depth_slice: None,
                resolve_target: None,
                ops: wgpu::Operations {
                    load: wgpu::LoadOp::Clear(wgpu::Color {
                        r: f64::from(background[0]),
                        g: f64::from(background[1]),
                        b: f64::from(background[2]),
                        a: 1.0,
                    }),
                    store: wgpu::StoreOp::Store,
                },
            })],
            depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
                view: &target.depth_view,
                depth_ops: Some(wgpu::Operations {
                    load: wgpu::LoadOp::Clear(1.0),
                    store: wgpu::StoreOp::Discard,
                }),
                stencil_ops: None,
            }),
            timestamp_writes: None,
            occlusion_query_set: None,
            multiview_mask: None,
        });
        if count > 0 {
            // The points' colour and depth first, so that the lines are depth-tested.
            pass.set_pipeline(&self.resolve_pipeline);
            pass.set_bind_group(0, &target.resolve_group, &[]);
            pass.draw(0..3, 0..1);
        }
        if let (Some((vertices, indices, n)), true) = (&self.mesh, self.show_mesh) {
            pass.set_pipeline(&self.mesh_pipeline);
            pass.set_bind_group(0, &self.camera_group, &[]);
            pass.set_vertex_buffer(0, vertices.slice(..));
            pass.set_index_buffer(indices.slice(..), wgpu::IndexFormat::Uint32);
            pass.draw_indexed(0..*n, 0, 0..1);
        }
        if let Some((buf, n)) = &self.lines {
            pass.set_pipeline(&self.line_pipeline);
            pass.set_bind_group(0, &self.camera_group, &[]);
            pass.set_vertex_buffer(0, buf.slice(..));
            pass.draw(0..*n, 0..1);
        }
    }

    /// Copies the offscreen image into `pass` (the callback's viewport).
    pub fn blit(&self, pass: &mut wgpu::RenderPass<'static>) {
        if let Some(t) = &self.target {
            pass.set_pipeline(&self.blit_pipeline);
            pass.set_bind_group(0, &t.blit_group, &[]);
            pass.draw(0..3, 0..1);
        }
    }

    /// The offscreen colour texture (for read-back in benchmarks and tests).
    pub fn colour_texture(&self) -> Option<&wgpu::Texture> {
        self.target.as_ref().map(|t| &t.colour)
    }

    /// Number of uploaded mesh triangle indices (3 per triangle).
    pub fn mesh_indices(&self) -> u32 {
        self.mesh.as_ref().map_or(0, |m| m.2)
    }

    /// Numbers of uploaded points and line vertices.
    pub fn counts(&self) -> (u32, u32) {
        (
            self.points.as_ref().map_or(0, |p| p.1),
            self.lines.as_ref().map_or(0, |p| p.1),
        )
    }
}

/// The paint callback of one 3D view.
pub struct SceneCallback {
    /// What to draw.
    pub geometry: Arc<Geometry>,
    /// Camera matrix.
    pub clip_from_world: Mat4,
    /// Viewport size, pixels.
    pub size_px: [u32; 2],
    /// Background colour (gamma-encoded RGB in 0..1).
    pub background: [f32; 3],
    /// Most points drawn (`u32::MAX` = all).
    pub point_budget: u32,
    /// Draw the points.
    pub show_points: bool,
    /// Draw the mesh (when the geometry has one).
    pub show_mesh: bool,
}

impl egui_wgpu::CallbackTrait for SceneCallback {
    fn prepare(
        &self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        _screen: &egui_wgpu::ScreenDescriptor,
        encoder: &mut wgpu::CommandEncoder,
        resources: &mut egui_wgpu::CallbackResources,
    ) -> Vec<wgpu::CommandBuffer> {
        if let Some(r) = resources.get_mut::<SceneRenderer>() {
            r.upload(device, &self.geometry);
            r.set_point_budget(self.point_budget);
            r.set_visible(self.show_points, self.show_mesh);
            r.render(
                device,
                queue,
                encoder,
                self.clip_from_world,
                self.size_px,
                self.background,
            );
        }
        Vec::new()
    }

    fn paint(
        &self,
        _info: egui::PaintCallbackInfo,
        pass: &mut wgpu::RenderPass<'static>,
        resources: &egui_wgpu::CallbackResources,
    ) {
        if let Some(r) = resources.get::<SceneRenderer>() {
            r.blit(pass);
        }
    }
}

/// Installs the renderer into an egui_wgpu render state (call once at start-up).
pub fn install(render_state: &egui_wgpu::RenderState, msaa_samples: u32) {
    let r = SceneRenderer::new(
        &render_state.device,
        render_state.target_format,
        msaa_samples,
        None,
    );
    render_state.renderer.write().callback_resources.insert(r);
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn orbit_camera_projects_target_to_centre_and_up_is_up() {
        let cam = OrbitCamera::default();
        let m = cam.clip_from_world(1.5);
        let c = m.project_point3(cam.target);
        assert!(c.x.abs() < 1e-5 && c.y.abs() < 1e-5, "{c}");
        assert!(c.z > 0.0 && c.z < 1.0);
        // A point above the target (world -y) appears above the centre (clip +y).
        let above = m.project_point3(cam.target + Vec3::new(0.0, -0.5, 0.0));
        assert!(above.y > 0.05, "{above}");
    }

    #[test]
    fn projection_maps_near_and_far_to_0_and_1() {
        let m = perspective_rh(1.0, 1.5, 0.1, 10.0);
        let n = m.project_point3(Vec3::new(0.0, 0.0, -0.1));
        let f = m.project_point3(Vec3::new(0.0, 0.0, -10.0));
        assert!(n.z.abs() < 1e-5 && (f.z - 1.0).abs() < 1e-5, "{n} {f}");
        let v = look_at_rh(Vec3::new(1.0, 2.0, 3.0), Vec3::ZERO, Vec3::Y);
        let p = v.transform_point3(Vec3::ZERO);
        assert!(p.x.abs() < 1e-5 && p.y.abs() < 1e-5 && p.z < 0.0, "{p}");
    }

    #[test]
    fn frame_bounds_sees_the_corners() {
        let mut cam = OrbitCamera::default();
        let b = (Vec3::new(-3.0, -1.0, 0.0), Vec3::new(5.0, 2.0, 9.0));
        cam.frame_bounds(b);
        let m = cam.clip_from_world(1.0);
        for x in [b.0.x, b.1.x] {
            for y in [b.0.y, b.1.y] {
                for z in [b.0.z, b.1.z] {
                    let p = m.project_point3(Vec3::new(x, y, z));
                    assert!(p.x.abs() <= 1.0 && p.y.abs() <= 1.0, "{p}");
                }
            }
        }
    }

    #[test]
    fn geometry_frustum_and_bounds() {
        let mut g = Geometry::default();
        assert!(g.bounds().is_none());
        g.add_frustum(&Se3::default(), 0.2, [255; 4]);
        assert_eq!(g.lines.len(), 16);
        let (lo, hi) = g.bounds().unwrap();
        assert!((hi.z - 0.2).abs() < 1e-6 && lo.z.abs() < 1e-6);
        assert!((hi.x - 0.1).abs() < 1e-6);
        assert_eq!(g.robust_bounds(), g.bounds());
    }

    #[test]
    fn interleave_is_a_permutation_with_spread_prefixes() {
        let v: Vec<Vertex> = (0..1000)
            .map(|i| Vertex::new(DVec3::new(f64::from(i), 0.0, 0.0), [0; 4]))
            .collect();
        let w = interleave(v.clone());
        let mut xs: Vec<i32> = w.iter().map(|v| v.position[0] as i32).collect();
        // The first 10 cover the range in steps of at most ~200.
        let mut head = xs[..10].to_vec();
        head.sort();
        assert!(head.windows(2).all(|p| p[1] - p[0] < 250), "{head:?}");
        xs.sort();
        assert_eq!(xs, (0..1000).collect::<Vec<i32>>());
    }
}
