// Image-domain surface normals from an inverse-depth map (thesis eq. 5.2).
// CPU mirror: src/segment/normals.rs (`normal_row`), same operations in the same order.
//
// rho(x, y) of a plane n.p = d is affine in normalised coordinates, so
// m = (fx rho_u, fy rho_v, rho - x fx rho_u - y fy rho_v) = n / d and the camera-facing unit
// normal is -m / |m|. Output: vec4(n, 1) per pixel, vec4(0) where invalid.

struct Params {
    width: u32,
    height: u32,
    step: u32,
    _pad: u32,
    fx: f32,
    fy: f32,
    cx: f32,
    cy: f32,
    jump_tolerance: f32,
    _pad1: f32,
    _pad2: f32,
    _pad3: f32,
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> inv_depth: array<f32>;
@group(0) @binding(2) var<storage, read_write> normals: array<vec4<f32>>;

// Inverse depth at (x, y), 0 outside the image or where not > 0 (NaN included).
fn rho_at(x: i32, y: i32) -> f32 {
    if (x < 0 || y < 0 || x >= i32(params.width) || y >= i32(params.height)) {
        return 0.0;
    }
    let v = inv_depth[u32(y) * params.width + u32(x)];
    return select(0.0, v, v > 0.0);
}

// Central difference, or the smaller one-sided difference across a discontinuity.
// Returns vec2(derivative, valid).
fn diff(minus: f32, centre: f32, plus: f32, tol: f32) -> vec2<f32> {
    let vm = minus > 0.0;
    let vp = plus > 0.0;
    let dm = centre - minus;
    let dp = plus - centre;
    if (vm && vp) {
        if (abs(dp - dm) <= tol) {
            return vec2<f32>(0.5 * (dm + dp), 1.0);
        }
        if (abs(dp) < abs(dm)) {
            return vec2<f32>(dp, 1.0);
        }
        return vec2<f32>(dm, 1.0);
    }
    if (vm) {
        return vec2<f32>(dm, 1.0);
    }
    if (vp) {
        return vec2<f32>(dp, 1.0);
    }
    return vec2<f32>(0.0, 0.0);
}

@compute @workgroup_size(16, 16, 1)
fn image_normals(@builtin(global_invocation_id) gid: vec3<u32>) {
    if (gid.x >= params.width || gid.y >= params.height) {
        return;
    }
    let idx = gid.y * params.width + gid.x;
    let x = i32(gid.x);
    let y = i32(gid.y);
    let r0 = rho_at(x, y);
    if (!(r0 > 0.0)) {
        normals[idx] = vec4<f32>(0.0);
        return;
    }
    let s = i32(max(params.step, 1u));
    let tol = params.jump_tolerance * r0;
    let gx = diff(rho_at(x - s, y), r0, rho_at(x + s, y), tol);
    let gy = diff(rho_at(x, y - s), r0, rho_at(x, y + s), tol);
    if (gx.y == 0.0 || gy.y == 0.0) {
        normals[idx] = vec4<f32>(0.0);
        return;
    }
    let inv_s = 1.0 / f32(s);
    let xn = (f32(gid.x) - params.cx) / params.fx;
    let yn = (f32(gid.y) - params.cy) / params.fy;
    let mx = params.fx * (gx.x * inv_s);
    let my = params.fy * (gy.x * inv_s);
    let mz = r0 - xn * mx - yn * my;
    let len = sqrt(mx * mx + my * my + mz * mz);
    if (!(len > 0.0) || len > 3.0e38) {
        normals[idx] = vec4<f32>(0.0);
        return;
    }
    normals[idx] = vec4<f32>(-mx / len, -my / len, -mz / len, 1.0);
}
