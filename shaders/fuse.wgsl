// Keyframe inverse-depth fusion by reverse warping (thesis 6.4.2, eq. 6.24-6.25).
// CPU mirror: src/slam/fusion.rs (`fuse_pixel`), same operations in the same order.
//
// For every keyframe pixel with inverse depth rho_k: its point is moved into the current
// frame (cur_from_kf), projected to the nearest pixel q; where the current frame has depth at
// q, the current point is moved back into the keyframe and its inverse depth rho' is compared
// with rho_k. Consistent measurements (|rho' - rho_k| <= tol, tol = tol_sigma = 3 sigma_W
// where set, else tol_abs + tol_rel rho_k) update
// rho_k <- (w rho_k + w_new rho') / (w + w_new), w <- min(w + w_new, w_max).
// counts[0]: keyframe pixels with depth; counts[1]: of those, landing on a current pixel with
// depth (with `occlusion`: consistent depth; covisibility numerator); counts[2]: fused;
// counts[3], counts[4]: the same as counts[0], counts[1] from the frame's side
// (`covisible_back`, eq. 6.10 takes the minimum of both ratios).

// Host mirror: `FuseUniform` in src/slam/fusion.rs (a test compares the layouts).
struct Params {
    width: u32,               // keyframe size, pixels
    height: u32,
    _pad0: u32,
    _pad1: u32,
    fx: f32,                  // intrinsics, pixels
    fy: f32,
    cx: f32,
    cy: f32,
    rot0: vec4<f32>,          // cur_from_kf rows, translation (m) in w
    rot1: vec4<f32>,
    rot2: vec4<f32>,
    inv0: vec4<f32>,          // kf_from_cur rows, translation (m) in w
    inv1: vec4<f32>,
    inv2: vec4<f32>,
    tol_abs: f32,             // consistency tolerance tol_abs + tol_rel rho, 1/m
    tol_rel: f32,
    new_weight: f32,          // weight of one measurement
    max_weight: f32,          // cap of the accumulated weight
    tol_sigma: f32,           // 3 sigma_W tolerance, 1/m (0: tol_abs + tol_rel rho)
    occlusion: u32,           // 1: inconsistent pixels are not covisible
    _pad2a: u32,
    _pad2b: u32,
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> cur_rho: array<f32>;
@group(0) @binding(2) var<storage, read_write> kf_rho: array<f32>;
@group(0) @binding(3) var<storage, read_write> kf_weight: array<f32>;
@group(0) @binding(4) var<storage, read_write> counts: array<atomic<u32>>;

fn xform(r0: vec4<f32>, r1: vec4<f32>, r2: vec4<f32>, p: vec3<f32>) -> vec3<f32> {
    return vec3<f32>(
        r0.x * p.x + r0.y * p.y + r0.z * p.z + r0.w,
        r1.x * p.x + r1.y * p.y + r1.z * p.z + r1.w,
        r2.x * p.x + r2.y * p.y + r2.z * p.z + r2.w,
    );
}

// Consistency tolerance at keyframe inverse depth rho (mirror: `FuseUniform::tolerance`).
fn tolerance(rho: f32) -> f32 {
    if (params.tol_sigma > 0.0) {
        return params.tol_sigma;
    }
    return params.tol_abs + params.tol_rel * rho;
}

@compute @workgroup_size(16, 16, 1)
fn fuse(@builtin(global_invocation_id) gid: vec3<u32>) {
    let w = params.width;
    let h = params.height;
    if (gid.x >= w || gid.y >= h) {
        return;
    }
    let i = gid.y * w + gid.x;
    let rho = kf_rho[i];
    if (!(rho > 0.0)) {
        return;
    }
    atomicAdd(&counts[0], 1u);
    let fx = params.fx;
    let fy = params.fy;
    let cx = params.cx;
    let cy = params.cy;
    let z = 1.0 / rho;
    let pk = vec3<f32>((f32(gid.x) - cx) / fx * z, (f32(gid.y) - cy) / fy * z, z);
    let pc = xform(params.rot0, params.rot1, params.rot2, pk);
    if (!(pc.z > 0.0)) {
        return;
    }
    let u = fx * pc.x / pc.z + cx;
    let v = fy * pc.y / pc.z + cy;
    let qx = floor(u + 0.5);
    let qy = floor(v + 0.5);
    if (!(qx >= 0.0 && qy >= 0.0 && qx <= f32(w - 1u) && qy <= f32(h - 1u))) {
        return;
    }
    let j = u32(qy) * w + u32(qx);
    let rc = cur_rho[j];
    if (!(rc > 0.0)) {
        return;
    }
    if (params.occlusion == 0u) {
        atomicAdd(&counts[1], 1u);
    }
    let zc = 1.0 / rc;
    let qc = vec3<f32>((qx - cx) / fx * zc, (qy - cy) / fy * zc, zc);
    let qk = xform(params.inv0, params.inv1, params.inv2, qc);
    if (!(qk.z > 0.0)) {
        return;
    }
    let rho_new = 1.0 / qk.z;
    if (abs(rho_new - rho) > tolerance(rho)) {
        return;
    }
    if (params.occlusion == 1u) {
        atomicAdd(&counts[1], 1u);
    }
    let wk = kf_weight[i];
    let wn = params.new_weight;
    kf_rho[i] = (wk * rho + wn * rho_new) / (wk + wn);
    kf_weight[i] = min(wk + wn, params.max_weight);
    atomicAdd(&counts[2], 1u);
}

// The frame side of the covisibility: current pixels with depth moved into the keyframe
// (kf_from_cur), landing on keyframe depth (consistent depth with `occlusion`).
// Mirror: `covisible_back` in src/slam/fusion.rs.
@compute @workgroup_size(16, 16, 1)
fn covisible_back(@builtin(global_invocation_id) gid: vec3<u32>) {
    let w = params.width;
    let h = params.height;
    if (gid.x >= w || gid.y >= h) {
        return;
    }
    let rc = cur_rho[gid.y * w + gid.x];
    if (!(rc > 0.0)) {
        return;
    }
    atomicAdd(&counts[3], 1u);
    let fx = params.fx;
    let fy = params.fy;
    let cx = params.cx;
    let cy = params.cy;
    let zc = 1.0 / rc;
    let pc = vec3<f32>((f32(gid.x) - cx) / fx * zc, (f32(gid.y) - cy) / fy * zc, zc);
    let pk = xform(params.inv0, params.inv1, params.inv2, pc);
    if (!(pk.z > 0.0)) {
        return;
    }
    let u = fx * pk.x / pk.z + cx;
    let v = fy * pk.y / pk.z + cy;
    let qx = floor(u + 0.5);
    let qy = floor(v + 0.5);
    if (!(qx >= 0.0 && qy >= 0.0 && qx <= f32(w - 1u) && qy <= f32(h - 1u))) {
        return;
    }
    let rk = kf_rho[u32(qy) * w + u32(qx)];
    if (!(rk > 0.0)) {
        return;
    }
    if (params.occlusion == 1u && abs(1.0 / pk.z - rk) > tolerance(rk)) {
        return;
    }
    atomicAdd(&counts[4], 1u);
}
