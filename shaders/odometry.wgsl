//! include: common.wgsl
// Dense RGB-ID odometry kernels (thesis 6.3): reverse warping of reference pixels into the
// current frame, photometric and inverse-depth residuals with their Jacobians, IRLS normal
// equations reduced per workgroup, residual samples for scale estimation, covisibility.
// CPU mirror: src/odometry/kernel.rs (same formulas, same order).

struct WarpParams {
    dims: vec4<u32>,   // width, height, level offset, sample count
    intr: vec4<f32>,   // fx, fy, cx, cy
    rot0: vec4<f32>,   // rows of R (cur_from_ref), .w = t
    rot1: vec4<f32>,
    rot2: vec4<f32>,
    robust: vec4<f32>, // sigma_I, sigma_W, nu_I, nu_W
    flags: vec4<u32>,  // estimator, term mask, geometric param (0 inv depth, 1 depth), sample offset
}

@group(0) @binding(0) var<uniform> P: WarpParams;
@group(0) @binding(1) var<storage, read> ref_photo: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read> ref_geo: array<vec4<f32>>;
@group(0) @binding(3) var<storage, read> cur_photo: array<vec4<f32>>;
@group(0) @binding(4) var<storage, read> cur_geo: array<vec4<f32>>;
@group(0) @binding(5) var<storage, read_write> out: array<f32>;

const WG: u32 = 128u;
const NPART: u32 = 30u;
var<workgroup> sh: array<f32, 256>; // 2 * WG, covisibility counts

struct Terms {
    photo_ok: bool,
    r_photo: f32,
    j_photo_t: vec3<f32>,
    j_photo_r: vec3<f32>,
    geo_ok: bool,
    r_geo: f32,
    j_geo_t: vec3<f32>,
    j_geo_r: vec3<f32>,
}

fn robust_weight(est: u32, z: f32, nu: f32) -> f32 {
    if (est == 1u) {
        let a = abs(z);
        if (a <= HUBER_K) { return 1.0; }
        return HUBER_K / a;
    }
    if (est == 2u) {
        let t = z / TUKEY_C;
        if (abs(t) < 1.0) { let s = 1.0 - t * t; return s * s; }
        return 0.0;
    }
    if (est == 3u) { return (nu + 1.0) / (nu + z * z); }
    return 1.0;
}

// Reference pixel i back-projected with its inverse depth and moved by cur_from_ref;
// .w = 0 where it has no depth. Mirror of `warp_point` in kernel.rs.
fn warp_point(i: u32) -> vec4<f32> {
    let w = P.dims.x;
    let rho = ref_geo[P.dims.z + i].x;
    if (rho <= 0.0) { return vec4<f32>(0.0); }
    let fx = P.intr.x; let fy = P.intr.y; let cx = P.intr.z; let cy = P.intr.w;
    let x = f32(i % w);
    let y = f32(i / w);
    let z = 1.0 / rho;
    let pr = vec3<f32>((x - cx) / fx * z, (y - cy) / fy * z, z);
    return vec4<f32>(
        P.rot0.x * pr.x + P.rot0.y * pr.y + P.rot0.z * pr.z + P.rot0.w,
        P.rot1.x * pr.x + P.rot1.y * pr.y + P.rot1.z * pr.z + P.rot1.w,
        P.rot2.x * pr.x + P.rot2.y * pr.y + P.rot2.z * pr.z + P.rot2.w,
        1.0);
}

fn pixel_terms(i: u32, want_j: bool) -> Terms {
    var t: Terms;
    t.photo_ok = false;
    t.geo_ok = false;
    let w = P.dims.x;
    let h = P.dims.y;
    let o = P.dims.z;
    let wq = warp_point(i);
    if (wq.w == 0.0) { return t; }
    let q = wq.xyz;
    let fx = P.intr.x; let fy = P.intr.y; let cx = P.intr.z; let cy = P.intr.w;
    if (q.z < MIN_DEPTH) { return t; }
    let iz = 1.0 / q.z;
    let u = fx * q.x * iz + cx;
    let v = fy * q.y * iz + cy;
    if (!(u >= 0.0 && v >= 0.0 && u < f32(w - 1u) && v < f32(h - 1u))) { return t; }
    let x0 = floor(u);
    let y0 = floor(v);
    let ax = u - x0;
    let ay = v - y0;
    let k = o + u32(y0) * w + u32(x0);
    let p00 = cur_photo[k]; let p10 = cur_photo[k + 1u];
    let p01 = cur_photo[k + w]; let p11 = cur_photo[k + w + 1u];
    let b00 = (1.0 - ax) * (1.0 - ay);
    let b10 = ax * (1.0 - ay);
    let b01 = (1.0 - ax) * ay;
    let b11 = ax * ay;
    let c = b00 * p00.xyz + b10 * p10.xyz + b01 * p01.xyz + b11 * p11.xyz;
    let terms = P.flags.y;
    if ((terms & 1u) != 0u) {
        t.photo_ok = true;
        t.r_photo = c.x - ref_photo[o + i].x;
        if (want_j) {
            let a = c.y * fx * iz;
            let b = c.z * fy * iz;
            let jt = vec3<f32>(a, b, -(a * q.x + b * q.y) * iz);
            t.j_photo_t = jt;
            t.j_photo_r = cross(q, jt);
        }
    }
    if ((terms & 2u) != 0u) {
        let xn = u32(floor(u + 0.5));
        let yn = u32(floor(v + 0.5));
        let g = cur_geo[o + yn * w + xn];
        if (g.x > 0.0 && g.y != INVALID_GRAD) {
            var res: f32; var gu: f32; var gv: f32; var dz: f32;
            // Nearest sample, or (flags.z bit 1) its first-order extension to (u, v).
            var rho = g.x;
            if ((P.flags.z & 2u) != 0u) {
                rho = g.x + g.y * (u - f32(xn)) + g.z * (v - f32(yn));
            }
            if ((P.flags.z & 1u) != 0u) {
                let ig2 = 1.0 / (rho * rho);
                res = 1.0 / rho - q.z; gu = -g.y * ig2; gv = -g.z * ig2; dz = -1.0;
            } else {
                res = rho - iz; gu = g.y; gv = g.z; dz = iz * iz;
            }
            t.geo_ok = true;
            t.r_geo = res;
            if (want_j) {
                let a = gu * fx * iz;
                let b = gv * fy * iz;
                let jt = vec3<f32>(a, b, -(a * q.x + b * q.y) * iz + dz);
                t.j_geo_t = jt;
                t.j_geo_r = cross(q, jt);
            }
        }
    }
    return t;
}

// The 30 partial sums live in 8 vec4 accumulators with constant indices (dynamic indexing of
// a private array becomes gathers/scatters on SIMD CPUs such as llvmpipe). Layout, as the
// CPU mirror's `PARTIAL_LEN` array: H upper triangle row-major (21), g (6), cost, n_I, n_W, 0.
struct Acc {
    a0: vec4<f32>, a1: vec4<f32>, a2: vec4<f32>, a3: vec4<f32>,
    a4: vec4<f32>, a5: vec4<f32>, a6: vec4<f32>, a7: vec4<f32>,
}

fn accumulate(acc: ptr<function, Acc>, jt: vec3<f32>, jr: vec3<f32>, r: f32, wt: f32) {
    let j0 = jt.x; let j1 = jt.y; let j2 = jt.z; let j3 = jr.x; let j4 = jr.y; let j5 = jr.z;
    let w0 = wt * j0; let w1 = wt * j1; let w2 = wt * j2; let w3 = wt * j3; let w4 = wt * j4; let w5 = wt * j5;
    (*acc).a0 += w0 * vec4<f32>(j0, j1, j2, j3);
    (*acc).a1 += vec4<f32>(w0 * j4, w0 * j5, w1 * j1, w1 * j2);
    (*acc).a2 += vec4<f32>(w1 * j3, w1 * j4, w1 * j5, w2 * j2);
    (*acc).a3 += vec4<f32>(w2 * j3, w2 * j4, w2 * j5, w3 * j3);
    (*acc).a4 += vec4<f32>(w3 * j4, w3 * j5, w4 * j4, w4 * j5);
    (*acc).a5 += vec4<f32>(w5 * j5, w0 * r, w1 * r, w2 * r);
    (*acc).a6 += vec4<f32>(w3 * r, w4 * r, w5 * r, wt * r * r);
}

// Pixel of residual sample k of `count` over `n` pixels: floor(k * n / count) without 32-bit
// overflow (k * n can exceed 2^32).
fn sample_pixel(k: u32, n: u32, count: u32) -> u32 {
    let q = n / count;
    let r = n % count;
    return k * q + (k * r) / count;
}

// The sample index whose pixel is i, or `count` when i is not sampled. sample_pixel is strictly
// increasing in k (count <= n), and the f32 estimate is off by at most one.
fn sample_slot(i: u32, n: u32, count: u32) -> u32 {
    var k = min(u32(f32(i) * f32(count) / f32(n)), count - 1u);
    if (sample_pixel(k, n, count) > i) {
        k -= 1u;
    } else if (k + 1u < count && sample_pixel(k + 1u, n, count) <= i) {
        k += 1u;
    }
    if (sample_pixel(k, n, count) == i) { return k; }
    return count;
}

// One invocation's share of the normal equations: pixels first, first + stride, ... With
// P.dims.w > 0 it also writes the residual sample at this pose (as sample_residuals would,
// from the same pixel_terms) at P.flags.w, so no second warp of the sampled pixels is needed.
fn accumulate_pixels(first: u32, stride: u32) -> Acc {
    var acc: Acc;
    let n = P.dims.x * P.dims.y;
    let est = P.flags.x;
    let count = min(P.dims.w, n);
    let o = P.flags.w;
    for (var i = first; i < n; i += stride) {
        let t = pixel_terms(i, true);
        if (count > 0u) {
            let k = sample_slot(i, n, count);
            if (k < count) {
                out[o + 2u * k] = select(INVALID_RESIDUAL, t.r_photo, t.photo_ok);
                out[o + 2u * k + 1u] = select(INVALID_RESIDUAL, t.r_geo, t.geo_ok);
            }
        }
        if (t.photo_ok) {
            let s = P.robust.x;
            let wt = robust_weight(est, t.r_photo / s, P.robust.z) / (s * s);
            accumulate(&acc, t.j_photo_t, t.j_photo_r, t.r_photo, wt);
            acc.a7.x += 1.0;
        }
        if (t.geo_ok) {
            let s = P.robust.y;
            let wt = robust_weight(est, t.r_geo / s, P.robust.w) / (s * s);
            accumulate(&acc, t.j_geo_t, t.j_geo_r, t.r_geo, wt);
            acc.a7.y += 1.0;
        }
    }
    return acc;
}

var<workgroup> shv: array<vec4<f32>, 1024>; // 8 * WG

// Shared-memory tree reduction, one partial per workgroup (devices without subgroups; the
// subgroup variant is in odometry_subgroup.wgsl).
@compute @workgroup_size(128)
fn normal_equations(@builtin(local_invocation_id) lid: vec3<u32>,
                    @builtin(workgroup_id) wid: vec3<u32>,
                    @builtin(num_workgroups) nwg: vec3<u32>) {
    let acc = accumulate_pixels(wid.x * WG + lid.x, nwg.x * WG);
    let l = lid.x;
    shv[l] = acc.a0; shv[WG + l] = acc.a1; shv[2u * WG + l] = acc.a2; shv[3u * WG + l] = acc.a3;
    shv[4u * WG + l] = acc.a4; shv[5u * WG + l] = acc.a5; shv[6u * WG + l] = acc.a6; shv[7u * WG + l] = acc.a7;
    workgroupBarrier();
    for (var s = WG / 2u; s > 0u; s = s / 2u) {
        if (l < s) {
            for (var k = 0u; k < 8u; k++) { shv[k * WG + l] += shv[k * WG + l + s]; }
        }
        workgroupBarrier();
    }
    if (l < 8u) {
        let v = shv[l * WG];
        let base = wid.x * NPART + 4u * l;
        // The last vec4 holds (n_I, n_W, 0, 0): only its first two lanes fit in NPART = 30.
        out[base] = v.x;
        out[base + 1u] = v.y;
        if (l < 7u) {
            out[base + 2u] = v.z;
            out[base + 3u] = v.w;
        }
    }
}

@compute @workgroup_size(128)
fn sample_residuals(@builtin(global_invocation_id) id: vec3<u32>) {
    let count = P.dims.w;
    if (id.x >= count) { return; }
    let n = P.dims.x * P.dims.y;
    let t = pixel_terms(sample_pixel(id.x, n, count), false);
    // flags.w: where the sample starts in `out` (after the normal-equation partials when both
    // run in one submission).
    let o = P.flags.w;
    out[o + 2u * id.x] = select(INVALID_RESIDUAL, t.r_photo, t.photo_ok);
    out[o + 2u * id.x + 1u] = select(INVALID_RESIDUAL, t.r_geo, t.geo_ok);
}

fn covisible(i: u32) -> u32 {
    let w = P.dims.x;
    let h = P.dims.y;
    let o = P.dims.z;
    let wq = warp_point(i);
    if (wq.w == 0.0) { return 0u; }
    let q = wq.xyz;
    let fx = P.intr.x; let fy = P.intr.y; let cx = P.intr.z; let cy = P.intr.w;
    if (q.z < MIN_DEPTH) { return 1u; }
    let u = fx * q.x / q.z + cx;
    let v = fy * q.y / q.z + cy;
    let xn = floor(u + 0.5);
    let yn = floor(v + 0.5);
    if (!(xn >= 0.0 && yn >= 0.0 && xn < f32(w) && yn < f32(h))) { return 1u; }
    if (cur_geo[o + u32(yn) * w + u32(xn)].x > 0.0) { return 2u; }
    return 1u;
}

// One invocation's (pixels with depth, covisible pixels) over first, first + stride, ...
fn count_covisible(first: u32, stride: u32) -> vec2<f32> {
    var with_depth = 0.0;
    var seen = 0.0;
    let n = P.dims.x * P.dims.y;
    for (var i = first; i < n; i += stride) {
        let c = covisible(i);
        if (c >= 1u) { with_depth += 1.0; }
        if (c == 2u) { seen += 1.0; }
    }
    return vec2<f32>(with_depth, seen);
}

@compute @workgroup_size(128)
fn covisibility(@builtin(local_invocation_id) lid: vec3<u32>,
                @builtin(workgroup_id) wid: vec3<u32>,
                @builtin(num_workgroups) nwg: vec3<u32>) {
    let c = count_covisible(wid.x * WG + lid.x, nwg.x * WG);
    sh[lid.x] = c.x;
    sh[WG + lid.x] = c.y;
    workgroupBarrier();
    for (var s = WG / 2u; s > 0u; s = s / 2u) {
        if (lid.x < s) {
            sh[lid.x] += sh[lid.x + s];
            sh[WG + lid.x] += sh[WG + lid.x + s];
        }
        workgroupBarrier();
    }
    if (lid.x == 0u) {
        out[2u * wid.x] = sh[0];
        out[2u * wid.x + 1u] = sh[WG];
    }
}
