//! include: common.wgsl
// Image pyramids and gradients (mirror: src/odometry/kernel.rs + cpu.rs).
// photo = (I, dI/du, dI/dv, 0), geo = (rho, drho/du, drho/dv, 0); all levels concatenated.

// Host mirror: `PyrParams` in src/odometry/kernel.rs (a test compares the layouts).
struct PyrParams {
    width: u32,       // destination level size, pixels
    height: u32,
    offset: u32,      // destination level offset, pixels
    src_offset: u32,  // source level offset (downsampling), pixels
    src_width: u32,   // source level size (downsampling), pixels
    src_height: u32,
    inv2_photo: f32,  // bilateral filter: 1 / (2 sigma_I^2)
    inv2_rho: f32,    // bilateral filter: 1 / (2 sigma_rho^2)
}

@group(0) @binding(0) var<uniform> P: PyrParams;
@group(0) @binding(1) var<storage, read> input: array<f32>; // level 0: I[0..n], rho[n..2n]
@group(0) @binding(2) var<storage, read_write> photo: array<vec4<f32>>;
@group(0) @binding(3) var<storage, read_write> geo: array<vec4<f32>>;

@compute @workgroup_size(16, 16)
fn pack_level0(@builtin(global_invocation_id) id: vec3<u32>) {
    let w = P.width;
    let h = P.height;
    if (id.x >= w || id.y >= h) { return; }
    let i = id.y * w + id.x;
    let n = w * h;
    let rho = input[n + i];
    var r = 0.0;
    // Rejects NaN (comparisons are false), infinities and non-positive values.
    if (rho > 0.0 && rho < 1e30) { r = rho; }
    photo[i] = vec4<f32>(input[i], 0.0, 0.0, 0.0);
    geo[i] = vec4<f32>(r, 0.0, 0.0, 0.0);
}

@compute @workgroup_size(16, 16)
fn downsample(@builtin(global_invocation_id) id: vec3<u32>) {
    let w = P.width;
    let h = P.height;
    if (id.x >= w || id.y >= h) { return; }
    let sw = P.src_width;
    let k = P.src_offset + 2u * id.y * sw + 2u * id.x;
    let i = 0.25 * (photo[k].x + photo[k + 1u].x + photo[k + sw].x + photo[k + sw + 1u].x);
    var s = 0.0;
    var n = 0.0;
    let r4 = vec4<f32>(geo[k].x, geo[k + 1u].x, geo[k + sw].x, geo[k + sw + 1u].x);
    for (var j = 0u; j < 4u; j++) {
        if (r4[j] > 0.0) { s += r4[j]; n += 1.0; }
    }
    var r = 0.0;
    if (n > 0.0) { r = s / n; }
    let d = P.offset + id.y * w + id.x;
    photo[d] = vec4<f32>(i, 0.0, 0.0, 0.0);
    geo[d] = vec4<f32>(r, 0.0, 0.0, 0.0);
}

// Level 1 straight from the level-0 input planes, for frames whose level 0 is neither
// optimised nor read: the values are those of `pack_level0` then `downsample` (same
// sanitising, same sums in the same order), without writing level 0.
@compute @workgroup_size(16, 16)
fn downsample_input(@builtin(global_invocation_id) id: vec3<u32>) {
    let w = P.width;
    let h = P.height;
    if (id.x >= w || id.y >= h) { return; }
    let sw = P.src_width;
    let n0 = sw * P.src_height;
    let k = 2u * id.y * sw + 2u * id.x;
    let i = 0.25 * (input[k] + input[k + 1u] + input[k + sw] + input[k + sw + 1u]);
    var s = 0.0;
    var n = 0.0;
    let r4 = vec4<f32>(input[n0 + k], input[n0 + k + 1u], input[n0 + k + sw], input[n0 + k + sw + 1u]);
    for (var j = 0u; j < 4u; j++) {
        // pack_level0's test: NaN, infinities and non-positive values are invalid.
        let rho = r4[j];
        if (rho > 0.0 && rho < 1e30) { s += rho; n += 1.0; }
    }
    var r = 0.0;
    if (n > 0.0) { r = s / n; }
    let d = P.offset + id.y * w + id.x;
    photo[d] = vec4<f32>(i, 0.0, 0.0, 0.0);
    geo[d] = vec4<f32>(r, 0.0, 0.0, 0.0);
}

fn one_axis(l: f32, c: f32, r: f32, has_l: bool, has_r: bool) -> f32 {
    let lv = has_l && l > 0.0;
    let rv = has_r && r > 0.0;
    if (lv && rv) { return 0.5 * (r - l); }
    if (rv) { return r - c; }
    if (lv) { return c - l; }
    return INVALID_GRAD;
}

// Central-difference gradients of the values in `lane` (0: the level's own values; 3: the
// bilateral-filtered ones) at (x, y) of the level at offset `o`: (dI/du, dI/dv, drho/du,
// drho/dv), INVALID_GRAD for inverse depth across discontinuities or holes
// (mirror: kernel.rs `gradients_of_lane`).
fn level_gradients(o: u32, w: u32, h: u32, x: u32, y: u32, lane: u32) -> vec4<f32> {
    let xl = select(x - 1u, 0u, x == 0u);
    let xr = min(x + 1u, w - 1u);
    let yu = select(y - 1u, 0u, y == 0u);
    let yd = min(y + 1u, h - 1u);
    let gx = 0.5 * (photo[o + y * w + xr][lane] - photo[o + y * w + xl][lane]);
    let gy = 0.5 * (photo[o + yd * w + x][lane] - photo[o + yu * w + x][lane]);
    let rc = geo[o + y * w + x][lane];
    let gdx = one_axis(geo[o + y * w + xl][lane], rc, geo[o + y * w + xr][lane], x > 0u, x + 1u < w);
    let gdy = one_axis(geo[o + yu * w + x][lane], rc, geo[o + yd * w + x][lane], y > 0u, y + 1u < h);
    var gg = vec2<f32>(INVALID_GRAD, INVALID_GRAD);
    let lim = MAX_REL_GRAD * rc;
    if (rc > 0.0 && gdx != INVALID_GRAD && gdy != INVALID_GRAD && abs(gdx) <= lim && abs(gdy) <= lim) {
        gg = vec2<f32>(gdx, gdy);
    }
    return vec4<f32>(gx, gy, gg.x, gg.y);
}

@compute @workgroup_size(16, 16)
fn gradients(@builtin(global_invocation_id) id: vec3<u32>) {
    let w = P.width;
    let h = P.height;
    if (id.x >= w || id.y >= h) { return; }
    let c = P.offset + id.y * w + id.x;
    let g = level_gradients(P.offset, w, h, id.x, id.y, 0u);
    // Only the gradient lanes: .x is the level's value and .w was zeroed when the level was
    // written (each stored scalar is a per-lane loop on SIMD CPU drivers such as llvmpipe).
    photo[c].y = g.x;
    photo[c].z = g.y;
    geo[c].y = g.z;
    geo[c].z = g.w;
}

// The covariance pass (thesis 6.20, 6.21) works on a copy of one level: `bilateral` writes
// the bilateral-filtered intensity and inverse depth into .w (reading only .x), then
// `filtered_gradients` writes their gradients into .y/.z. The level is (width, height,
// offset); inv2_photo and inv2_rho scale the Cauchy range kernel (flat spatial kernel).
const BILATERAL_RADIUS: u32 = 2u;

@compute @workgroup_size(16, 16)
fn bilateral(@builtin(global_invocation_id) id: vec3<u32>) {
    let w = P.width;
    let h = P.height;
    if (id.x >= w || id.y >= h) { return; }
    let o = P.offset;
    let inv_i = P.inv2_photo;
    let inv_r = P.inv2_rho;
    let c = o + id.y * w + id.x;
    let ic = photo[c].x;
    let rc = geo[c].x;
    var si = 0.0;
    var wi = 0.0;
    var sr = 0.0;
    var wr = 0.0;
    let r = BILATERAL_RADIUS;
    let y0 = select(id.y - r, 0u, id.y < r);
    let x0 = select(id.x - r, 0u, id.x < r);
    let y1 = min(id.y + r + 1u, h);
    let x1 = min(id.x + r + 1u, w);
    for (var v = y0; v < y1; v++) {
        for (var u = x0; u < x1; u++) {
            let k = o + v * w + u;
            let ik = photo[k].x;
            let di = ik - ic;
            let a = 1.0 / (1.0 + inv_i * di * di);
            si += a * ik;
            wi += a;
            let rk = geo[k].x;
            if (rc > 0.0 && rk > 0.0) {
                let dr = rk - rc;
                let b = 1.0 / (1.0 + inv_r * dr * dr);
                sr += b * rk;
                wr += b;
            }
        }
    }
    var rf = 0.0;
    if (rc > 0.0 && wr > 0.0) { rf = sr / wr; }
    photo[c].w = si / wi;
    geo[c].w = rf;
}

@compute @workgroup_size(16, 16)
fn filtered_gradients(@builtin(global_invocation_id) id: vec3<u32>) {
    let w = P.width;
    let h = P.height;
    if (id.x >= w || id.y >= h) { return; }
    let c = P.offset + id.y * w + id.x;
    let g = level_gradients(P.offset, w, h, id.x, id.y, 3u);
    photo[c].y = g.x;
    photo[c].z = g.y;
    geo[c].y = g.z;
    geo[c].z = g.w;
}
