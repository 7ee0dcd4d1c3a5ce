// Undistortion of a raw frame through a precomputed remap table (see src/io/undistort.rs).
// CPU mirror: `UndistortMap::remap_bilinear` / `remap_nearest`, same operations in the same
// order.
//
// One table entry per output pixel: (index of the top-left bilinear source pixel, x weight
// bits, y weight bits, index of the nearest source pixel or 0xffffffff when it lies outside
// the raw image). Intensity is resampled bilinearly (border replicated by the table's clamp),
// inverse depth by nearest neighbour (0 outside), so depths are never blended across edges.
// Output: intensity in out[0 .. n], inverse depth in out[n .. 2n].

struct Params {
    width: u32,
    height: u32,
    _pad0: u32,
    _pad1: u32,
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> table: array<vec4<u32>>;
@group(0) @binding(2) var<storage, read> raw_intensity: array<f32>;
@group(0) @binding(3) var<storage, read> raw_inv_depth: array<f32>;
@group(0) @binding(4) var<storage, read_write> out: array<f32>;

const OUTSIDE: u32 = 0xffffffffu;

@compute @workgroup_size(16, 16, 1)
fn undistort(@builtin(global_invocation_id) gid: vec3<u32>) {
    let w = params.width;
    let h = params.height;
    if (gid.x >= w || gid.y >= h) {
        return;
    }
    let o = gid.y * w + gid.x;
    let t = table[o];
    let i = t.x;
    let wx = bitcast<f32>(t.y);
    let wy = bitcast<f32>(t.z);
    let step_x = select(0u, 1u, w > 1u);
    let step_y = select(0u, w, h > 1u);
    let a = raw_intensity[i];
    let b = raw_intensity[i + step_x];
    let c = raw_intensity[i + step_y];
    let d = raw_intensity[i + step_y + step_x];
    let top = a + (b - a) * wx;
    let bottom = c + (d - c) * wx;
    out[o] = top + (bottom - top) * wy;
    var rho = 0.0;
    if (t.w != OUTSIDE) {
        rho = raw_inv_depth[t.w];
    }
    out[w * h + o] = rho;
}
