// Points of the 3D view splatted by compute instead of rasterised: software rasterisers
// (lavapipe) set up every point as a primitive (about 2 M points/s on two cores), while a
// compute pass projects them in SIMD lanes. One pixel per point, nearest point wins:
//   splat_depth   per point: atomicMax of the depth key (0 = empty; nearer = larger)
//   splat_colour  per point: the point whose key won writes its colour
//   fs_resolve    per pixel of the offscreen target: colour and depth of the winner (so the
//                 line segments drawn afterwards are depth-tested against the points)

struct Camera {
    clip_from_world: mat4x4<f32>,
};

struct Params {
    width: u32,
    height: u32,
    count: u32,
    // Points per row of workgroups (dispatches wider than 65535 groups use y).
    row: u32,
};

struct Point {
    x: f32,
    y: f32,
    z: f32,
    colour: u32,
};

@group(0) @binding(0) var<uniform> camera: Camera;
@group(0) @binding(1) var<uniform> params: Params;
@group(0) @binding(2) var<storage, read> points: array<Point>;
@group(0) @binding(3) var<storage, read_write> depth: array<atomic<u32>>;
@group(0) @binding(4) var<storage, read_write> colour: array<u32>;

// Pixel index and depth key of point i, or key 0 when it is not in view.
fn project(i: u32) -> vec2<u32> {
    let p = points[i];
    let c = camera.clip_from_world * vec4<f32>(p.x, p.y, p.z, 1.0);
    if (c.w <= 0.0) {
        return vec2<u32>(0u, 0u);
    }
    let ndc = c.xyz / c.w;
    if (ndc.x < -1.0 || ndc.x >= 1.0 || ndc.y <= -1.0 || ndc.y > 1.0 || ndc.z < 0.0 || ndc.z > 1.0) {
        return vec2<u32>(0u, 0u);
    }
    let px = min(u32((ndc.x * 0.5 + 0.5) * f32(params.width)), params.width - 1u);
    let py = min(u32((0.5 - ndc.y * 0.5) * f32(params.height)), params.height - 1u);
    // Non-negative floats order like their bits; 1.0 has bits 0x3f800000, so the key of any
    // depth in [0, 1] is > 0.
    return vec2<u32>(py * params.width + px, 0xffffffffu - bitcast<u32>(ndc.z));
}

@compute @workgroup_size(256)
fn splat_depth(@builtin(global_invocation_id) g: vec3<u32>) {
    let i = g.y * params.row + g.x;
    if (i >= params.count) {
        return;
    }
    let s = project(i);
    if (s.y != 0u) {
        atomicMax(&depth[s.x], s.y);
    }
}

@compute @workgroup_size(256)
fn splat_colour(@builtin(global_invocation_id) g: vec3<u32>) {
    let i = g.y * params.row + g.x;
    if (i >= params.count) {
        return;
    }
    let s = project(i);
    if (s.y != 0u && atomicLoad(&depth[s.x]) == s.y) {
        colour[s.x] = points[i].colour;
    }
}

@group(0) @binding(0) var<uniform> resolve_params: Params;
@group(0) @binding(1) var<storage, read> resolve_depth: array<u32>;
@group(0) @binding(2) var<storage, read> resolve_colour: array<u32>;

@vertex
fn vs_resolve(@builtin(vertex_index) i: u32) -> @builtin(position) vec4<f32> {
    let x = f32((i << 1u) & 2u);
    let y = f32(i & 2u);
    return vec4<f32>(x * 2.0 - 1.0, 1.0 - y * 2.0, 0.0, 1.0);
}

struct ResolveOut {
    @location(0) colour: vec4<f32>,
    @builtin(frag_depth) depth: f32,
};

@fragment
fn fs_resolve(@builtin(position) pos: vec4<f32>) -> ResolveOut {
    let idx = u32(pos.y) * resolve_params.width + u32(pos.x);
    let key = resolve_depth[idx];
    if (key == 0u) {
        discard;
    }
    var out: ResolveOut;
    out.colour = unpack4x8unorm(resolve_colour[idx]);
    out.depth = bitcast<f32>(0xffffffffu - key);
    return out;
}
