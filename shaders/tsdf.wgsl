// TSDF integration of one frame into the active voxel blocks (thesis 4.5.5).
// CPU mirror: src/tsdf/integrate.rs (`integrate_block`; `update_row` does the per-voxel update
// below on eight voxels at once as SIMD lanes, with the same operations in the same order).
//
// One workgroup per active block (8x8 invocations, each walks the 8 voxels of a z column).
// Voxel g (global integer coordinates) sits at g * voxel_size in the world; it is moved into
// the camera, projected to the nearest pixel (three divisions per voxel, no floor), and where
// that pixel's inverse depth rho is in
// range the projective signed distance sdf = 1/rho - z_voxel updates the voxel when
// sdf >= -mu(z), mu(z) = max(trunc_min, trunc_sigmas * rho_sigma * z^2): tsdf is the weighted
// mean of min(sdf, mu) with weight rho^4 (inverse depth variance relative to 1 m), colour the
// weighted mean per channel rounded half up, weight capped at max_weight. Blocks are
// allocated by the host, so the kernel needs neither a hash table nor atomics.

// Host mirror: `IntegrateUniform` in src/tsdf/integrate.rs (a test compares the layouts).
struct Params {
    width: u32,               // frame size, pixels
    height: u32,
    active_count: u32,        // entries of `blocks` (the active list)
    has_colour: u32,          // 1 when rgb_img holds the frame's colour
    fx: f32,                  // intrinsics, pixels
    fy: f32,
    cx: f32,
    cy: f32,
    rot0: vec4<f32>,          // camera_from_world rows, translation (m) in w
    rot1: vec4<f32>,
    rot2: vec4<f32>,
    voxel_size: f32,          // m
    rho_sigma: f32,           // inverse-depth noise, 1/m
    trunc_min: f32,           // m
    trunc_sigmas: f32,        // truncation in depth sigmas
    max_weight: f32,
    min_rho: f32,             // valid inverse depth range, 1/m
    max_rho: f32,
    _pad: u32,
}

// Host mirror: `Voxel` in src/tsdf/integrate.rs.
struct Voxel {
    tsdf: f32,                // m, positive in front of the surface
    weight: f32,
    rgb: u32,                 // 0x00BBGGRR
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> rho_img: array<f32>;
@group(0) @binding(2) var<storage, read> rgb_img: array<u32>;
@group(0) @binding(3) var<storage, read> blocks: array<vec4<i32>>;
@group(0) @binding(4) var<storage, read_write> voxels: array<Voxel>;

fn blend(old: u32, cur: u32, w: f32, wn: f32, inv_wt: f32) -> u32 {
    let v = (f32(old) * w + f32(cur) * wn) * inv_wt;
    return min(u32(v + 0.5), 255u);
}

fn update_voxel(g: vec3<i32>, v: Voxel) -> Voxel {
    let s = params.voxel_size;
    let pw = vec3<f32>(f32(g.x) * s, f32(g.y) * s, f32(g.z) * s);
    let r0 = params.rot0;
    let r1 = params.rot1;
    let r2 = params.rot2;
    let pc = vec3<f32>(
        r0.x * pw.x + r0.y * pw.y + r0.z * pw.z + r0.w,
        r1.x * pw.x + r1.y * pw.y + r1.z * pw.z + r1.w,
        r2.x * pw.x + r2.y * pw.y + r2.z * pw.z + r2.w,
    );
    if (!(pc.z > 0.0)) {
        return v;
    }
    // Range-checked before the truncation, which then floors (the values are >= 0).
    let inv_z = 1.0 / pc.z;
    let qx = params.fx * pc.x * inv_z + params.cx + 0.5;
    let qy = params.fy * pc.y * inv_z + params.cy + 0.5;
    if (!(qx >= 0.0 && qy >= 0.0 && qx < f32(params.width) && qy < f32(params.height))) {
        return v;
    }
    let j = u32(qy) * params.width + u32(qx);
    let r = rho_img[j];
    if (!(r >= params.min_rho && r <= params.max_rho)) {
        return v;
    }
    let z = 1.0 / r;
    let sdf = z - pc.z;
    let mu = max(params.trunc_min, params.trunc_sigmas * (params.rho_sigma * z * z));
    if (sdf < -mu) {
        return v;
    }
    let d = min(sdf, mu);
    let wn = (r * r) * (r * r);
    let w = v.weight;
    let wt = w + wn;
    let inv_wt = 1.0 / wt;
    var res: Voxel;
    res.tsdf = (v.tsdf * w + d * wn) * inv_wt;
    res.weight = min(wt, params.max_weight);
    res.rgb = v.rgb;
    if (params.has_colour != 0u) {
        let c = rgb_img[j];
        res.rgb = blend(v.rgb & 255u, c & 255u, w, wn, inv_wt)
            | (blend((v.rgb >> 8u) & 255u, (c >> 8u) & 255u, w, wn, inv_wt) << 8u)
            | (blend((v.rgb >> 16u) & 255u, (c >> 16u) & 255u, w, wn, inv_wt) << 16u);
    }
    return res;
}

@compute @workgroup_size(8, 8, 1)
fn integrate(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let b = wg.y * 65535u + wg.x;
    if (b >= params.active_count) {
        return;
    }
    let a = blocks[b];
    let base = u32(a.w) * 512u;
    for (var z = 0u; z < 8u; z++) {
        let i = base + (z * 8u + lid.y) * 8u + lid.x;
        let g = vec3<i32>(a.x * 8 + i32(lid.x), a.y * 8 + i32(lid.y), a.z * 8 + i32(z));
        voxels[i] = update_voxel(g, voxels[i]);
    }
}
