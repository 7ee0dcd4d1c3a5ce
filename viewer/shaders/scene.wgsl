// 3D view of the viewer: line segments and mesh triangles drawn into an offscreen colour +
// depth target (after the splatted points, see splat.wgsl), then copied (blit) into egui's
// render pass.

struct Camera {
    clip_from_world: mat4x4<f32>,
};

@group(0) @binding(0) var<uniform> camera: Camera;

struct SceneOut {
    @builtin(position) position: vec4<f32>,
    @location(0) colour: vec4<f32>,
};

@vertex
fn vs_scene(@location(0) world: vec3<f32>, @location(1) colour: vec4<f32>) -> SceneOut {
    var out: SceneOut;
    out.position = camera.clip_from_world * vec4<f32>(world, 1.0);
    out.colour = colour;
    return out;
}

@fragment
fn fs_scene(in: SceneOut) -> @location(0) vec4<f32> {
    return in.colour;
}

struct MeshOut {
    @builtin(position) position: vec4<f32>,
    @location(0) colour: vec4<f32>,
    @location(1) world: vec3<f32>,
};

@vertex
fn vs_mesh(@location(0) world: vec3<f32>, @location(1) colour: vec4<f32>) -> MeshOut {
    var out: MeshOut;
    out.position = camera.clip_from_world * vec4<f32>(world, 1.0);
    out.colour = colour;
    out.world = world;
    return out;
}

// Flat shading from the triangle's normal (the screen-space derivatives of the world
// position), lit from both sides by a light from above (world -y is up) and a little from the
// side, so that walls and floors of the same colour differ.
@fragment
fn fs_mesh(in: MeshOut) -> @location(0) vec4<f32> {
    let c = cross(dpdx(in.world), dpdy(in.world));
    let len = length(c);
    // Degenerate (sub-pixel) triangles have no normal: ambient only.
    let n = select(vec3<f32>(0.0), c / len, len > 0.0);
    let light = normalize(vec3<f32>(0.4, -1.0, -0.3));
    let shade = 0.35 + 0.65 * abs(dot(n, light));
    return vec4<f32>(in.colour.rgb * shade, 1.0);
}

@group(0) @binding(0) var scene_colour: texture_2d<f32>;
@group(0) @binding(1) var scene_sampler: sampler;

struct BlitOut {
    @builtin(position) position: vec4<f32>,
    @location(0) uv: vec2<f32>,
};

// One triangle covering the viewport.
@vertex
fn vs_blit(@builtin(vertex_index) i: u32) -> BlitOut {
    let x = f32((i << 1u) & 2u);
    let y = f32(i & 2u);
    var out: BlitOut;
    out.position = vec4<f32>(x * 2.0 - 1.0, 1.0 - y * 2.0, 0.0, 1.0);
    out.uv = vec2<f32>(x, y);
    return out;
}

// egui works with gamma-encoded colours; an sRGB target expects linear ones.
@fragment
fn fs_blit_gamma(in: BlitOut) -> @location(0) vec4<f32> {
    return textureSample(scene_colour, scene_sampler, in.uv);
}

fn linear_from_gamma(c: vec3<f32>) -> vec3<f32> {
    let cutoff = c < vec3<f32>(0.04045);
    let lower = c / vec3<f32>(12.92);
    let higher = pow((c + vec3<f32>(0.055)) / vec3<f32>(1.055), vec3<f32>(2.4));
    return select(higher, lower, cutoff);
}

@fragment
fn fs_blit_linear(in: BlitOut) -> @location(0) vec4<f32> {
    let c = textureSample(scene_colour, scene_sampler, in.uv);
    return vec4<f32>(linear_from_gamma(c.rgb), c.a);
}
