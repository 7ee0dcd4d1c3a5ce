//! include: common.wgsl
// Dense RGB-ID odometry kernels (thesis 6.3): reverse warping of reference pixels into the
// current frame, photometric and inverse-depth residuals with their Jacobians (linearised in
// the current or the reference frame), IRLS normal
// equations reduced per workgroup, residual samples for scale estimation, covisibility.
// CPU mirror: src/odometry/kernel.rs (same formulas, same order).

// Host mirror: `WarpParams` in src/odometry/kernel.rs (a test compares the layouts).
struct WarpParams {
    width: u32,        // level size, pixels
    height: u32,
    offset: u32,       // level offset in the pyramid buffers, pixels
    samples: u32,      // residual sample size (0: none)
    fx: f32,           // level intrinsics, pixels
    fy: f32,
    cx: f32,
    cy: f32,
    rot0: vec4<f32>,   // rows of R (cur_from_ref), .w = t (m)
    rot1: vec4<f32>,
    rot2: vec4<f32>,
    sigma_photo: f32,  // robust scales and Student-t degrees of freedom
    sigma_geo: f32,
    nu_photo: f32,
    nu_geo: f32,
    estimator: u32,    // Estimator: 0 least squares, 1 Huber, 2 Tukey, 3 Student-t
    terms: u32,        // Terms: bit 0 photometric, bit 1 geometric
    geometric: u32,    // GeometricParam: 0 inverse depth, 1 depth
    sampling: u32,     // GeometricSampling: 0 nearest, 1 first-order
    occlusion: f32,    // covisibility's occlusion tolerance (geometric residual units; 0: none)
    mu_photo: f32,     // residual locations (eq. 4.26-4.27): weights and sums use r - mu
    mu_geo: f32,
    linearisation: u32, // Linearisation: 0 current frame (forward), 1 reference frame (inverse)
}

// One reduction partial (host mirror: `Partial` in src/odometry/kernel.rs).
struct Partial {
    h: array<f32, 21>, // upper triangle of sum w J^T J / sigma^2, row-major
    g: array<f32, 6>,  // sum w J^T r / sigma^2
    cost: f32,         // sum w (r / sigma)^2
    n_photo: f32,      // valid photometric residuals
    n_geo: f32,        // valid geometric residuals
}

@group(0) @binding(0) var<uniform> P: WarpParams;
@group(0) @binding(1) var<storage, read> ref_photo: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read> ref_geo: array<vec4<f32>>;
@group(0) @binding(3) var<storage, read> cur_photo: array<vec4<f32>>;
@group(0) @binding(4) var<storage, read> cur_geo: array<vec4<f32>>;
// Normal-equation partials, one per workgroup (or per subgroup).
@group(0) @binding(5) var<storage, read_write> partials: array<Partial>;
// Residual sample (r_photo, r_geo) per sampled pixel.
@group(0) @binding(6) var<storage, read_write> sample: array<vec2<f32>>;
// Covisibility counts (pixels with depth, covisible pixels) per workgroup (or subgroup).
@group(0) @binding(7) var<storage, read_write> counts: array<vec2<f32>>;

const WG: u32 = 128u;
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

// Reference pixel i back-projected with inverse depth rho (> 0): the point X_A, metres.
fn ref_point(i: u32, rho: f32) -> vec3<f32> {
    let w = P.width;
    let x = f32(i % w);
    let y = f32(i / w);
    let z = 1.0 / rho;
    return vec3<f32>((x - P.cx) / P.fx * z, (y - P.cy) / P.fy * z, z);
}

// Reference pixel i back-projected with its inverse depth and moved by cur_from_ref;
// .w = 0 where it has no depth. Mirror of `warp_point` in kernel.rs.
fn warp_point(i: u32) -> vec4<f32> {
    let rho = ref_geo[P.offset + i].x;
    if (rho <= 0.0) { return vec4<f32>(0.0); }
    let pr = ref_point(i, rho);
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
    let w = P.width;
    let h = P.height;
    let o = P.offset;
    let wq = warp_point(i);
    if (wq.w == 0.0) { return t; }
    let q = wq.xyz;
    let fx = P.fx; let fy = P.fy; let cx = P.cx; let cy = P.cy;
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
    // The linearisation point: the warped point (current frame), or the reference point
    // X_A with the reference pixel's gradients (reference frame, P.linearisation == 1).
    let reference = P.linearisation == 1u;
    let ga = ref_geo[o + i];
    var jq = q;
    var jiz = iz;
    if (reference) {
        jq = ref_point(i, ga.x);
        jiz = ga.x;
    }
    if ((P.terms & 1u) != 0u) {
        t.photo_ok = true;
        let rp = ref_photo[o + i];
        t.r_photo = c.x - rp.x;
        if (want_j) {
            var gx = c.y;
            var gy = c.z;
            if (reference) { gx = rp.y; gy = rp.z; }
            let a = gx * fx * jiz;
            let b = gy * fy * jiz;
            let jt = vec3<f32>(a, b, -(a * jq.x + b * jq.y) * jiz);
            t.j_photo_t = jt;
            t.j_photo_r = cross(jq, jt);
        }
    }
    if ((P.terms & 2u) != 0u) {
        let xn = u32(floor(u + 0.5));
        let yn = u32(floor(v + 0.5));
        let g = cur_geo[o + yn * w + xn];
        if (g.x > 0.0 && g.y != INVALID_GRAD && (!reference || ga.y != INVALID_GRAD)) {
            var res: f32; var gu: f32; var gv: f32; var dz: f32;
            var ok = true;
            // Nearest sample, or its first-order extension to (u, v).
            var rho = g.x;
            if (P.sampling == 1u) {
                rho = g.x + g.y * (u - f32(xn)) + g.z * (v - f32(yn));
            }
            if (reference) {
                // W_B*(p): the sample as the point q / (rho q_z) of B, moved into A by T^-1;
                // its depth there is R's third column dotted with (point - t).
                let s = 1.0 / (rho * q.z);
                let d = vec3<f32>(q.x * s - P.rot0.w, q.y * s - P.rot1.w, q.z * s - P.rot2.w);
                let za = P.rot0.z * d.x + P.rot1.z * d.y + P.rot2.z * d.z;
                ok = za >= MIN_DEPTH;
                if (P.geometric == 1u) {
                    let ig2 = 1.0 / (ga.x * ga.x);
                    res = za - jq.z; gu = -ga.y * ig2; gv = -ga.z * ig2; dz = -1.0;
                } else {
                    res = 1.0 / za - ga.x; gu = ga.y; gv = ga.z; dz = ga.x * ga.x;
                }
            } else if (P.geometric == 1u) {
                let ig2 = 1.0 / (rho * rho);
                res = 1.0 / rho - q.z; gu = -g.y * ig2; gv = -g.z * ig2; dz = -1.0;
            } else {
                res = rho - iz; gu = g.y; gv = g.z; dz = iz * iz;
            }
            t.geo_ok = ok;
            t.r_geo = res;
            if (want_j) {
                let a = gu * fx * jiz;
                let b = gv * fy * jiz;
                let jt = vec3<f32>(a, b, -(a * jq.x + b * jq.y) * jiz + dz);
                t.j_geo_t = jt;
                t.j_geo_r = cross(jq, jt);
            }
        }
    }
    return t;
}

// The 30 sums of a `Partial` live in 8 vec4 accumulators with constant indices (dynamic
// indexing of a private array becomes gathers/scatters on SIMD CPUs such as llvmpipe), in the
// order of `Partial`'s fields: a0..a4 and a5.x the 21 entries of h, a5.yzw and a6.xyz g,
// a6.w the cost, a7.xy the counts.
struct Acc {
    a0: vec4<f32>, a1: vec4<f32>, a2: vec4<f32>, a3: vec4<f32>,
    a4: vec4<f32>, a5: vec4<f32>, a6: vec4<f32>, a7: vec4<f32>,
}

fn to_partial(a0: vec4<f32>, a1: vec4<f32>, a2: vec4<f32>, a3: vec4<f32>,
              a4: vec4<f32>, a5: vec4<f32>, a6: vec4<f32>, a7: vec2<f32>) -> Partial {
    return Partial(
        array<f32, 21>(a0.x, a0.y, a0.z, a0.w, a1.x, a1.y, a1.z, a1.w, a2.x, a2.y, a2.z, a2.w,
                       a3.x, a3.y, a3.z, a3.w, a4.x, a4.y, a4.z, a4.w, a5.x),
        array<f32, 6>(a5.y, a5.z, a5.w, a6.x, a6.y, a6.z),
        a6.w, a7.x, a7.y);
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
// P.samples > 0 it also writes the residual sample at this pose (as sample_residuals would,
// from the same pixel_terms), so no second warp of the sampled pixels is needed.
fn accumulate_pixels(first: u32, stride: u32) -> Acc {
    var acc: Acc;
    let n = P.width * P.height;
    let est = P.estimator;
    let count = min(P.samples, n);
    for (var i = first; i < n; i += stride) {
        let t = pixel_terms(i, true);
        if (count > 0u) {
            let k = sample_slot(i, n, count);
            if (k < count) {
                sample[k] = vec2<f32>(select(INVALID_RESIDUAL, t.r_photo, t.photo_ok),
                                      select(INVALID_RESIDUAL, t.r_geo, t.geo_ok));
            }
        }
        if (t.photo_ok) {
            let s = P.sigma_photo;
            let r = t.r_photo - P.mu_photo;
            let wt = robust_weight(est, r / s, P.nu_photo) / (s * s);
            accumulate(&acc, t.j_photo_t, t.j_photo_r, r, wt);
            acc.a7.x += 1.0;
        }
        if (t.geo_ok) {
            let s = P.sigma_geo;
            let r = t.r_geo - P.mu_geo;
            let wt = robust_weight(est, r / s, P.nu_geo) / (s * s);
            accumulate(&acc, t.j_geo_t, t.j_geo_r, r, wt);
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
    if (l == 0u) {
        partials[wid.x] = to_partial(shv[0], shv[WG], shv[2u * WG], shv[3u * WG], shv[4u * WG],
                                     shv[5u * WG], shv[6u * WG], shv[7u * WG].xy);
    }
}

@compute @workgroup_size(128)
fn sample_residuals(@builtin(global_invocation_id) id: vec3<u32>) {
    let count = P.samples;
    if (id.x >= count) { return; }
    let n = P.width * P.height;
    let t = pixel_terms(sample_pixel(id.x, n, count), false);
    sample[id.x] = vec2<f32>(select(INVALID_RESIDUAL, t.r_photo, t.photo_ok),
                             select(INVALID_RESIDUAL, t.r_geo, t.geo_ok));
}

fn covisible(i: u32) -> u32 {
    let w = P.width;
    let h = P.height;
    let o = P.offset;
    let wq = warp_point(i);
    if (wq.w == 0.0) { return 0u; }
    let q = wq.xyz;
    let fx = P.fx; let fy = P.fy; let cx = P.cx; let cy = P.cy;
    if (q.z < MIN_DEPTH) { return 1u; }
    let u = fx * q.x / q.z + cx;
    let v = fy * q.y / q.z + cy;
    let xn = floor(u + 0.5);
    let yn = floor(v + 0.5);
    if (!(xn >= 0.0 && yn >= 0.0 && xn < f32(w) && yn < f32(h))) { return 1u; }
    let rc = cur_geo[o + u32(yn) * w + u32(xn)].x;
    if (!(rc > 0.0)) { return 1u; }
    if (P.occlusion > 0.0) {
        // The thesis' occlusion condition (eq. 4.33) in the residuals' parametrisation.
        var r = rc - 1.0 / q.z;
        if (P.geometric == 1u) { r = 1.0 / rc - q.z; }
        if (!(abs(r) < P.occlusion)) { return 1u; }
    }
    return 2u;
}

// One invocation's (pixels with depth, covisible pixels) over first, first + stride, ...
fn count_covisible(first: u32, stride: u32) -> vec2<f32> {
    var with_depth = 0.0;
    var seen = 0.0;
    let n = P.width * P.height;
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
        counts[wid.x] = vec2<f32>(sh[0], sh[WG]);
    }
}
