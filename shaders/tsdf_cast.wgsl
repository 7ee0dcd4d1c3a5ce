//! include: tsdf_blocks.wgsl
// Ray casting of the TSDF volume (KinectFusion's surface prediction): depth, colour and
// optionally normals of the first zero crossing from + to - along each pixel's ray.
// CPU mirror: src/tsdf/raycast.rs (`cast`), same f32 operations in the same order.
//
// One invocation per pixel. The ray starts at min_depth and marches: where the trilinear TSDF
// is defined (all 8 voxels observed) by max(min(|tsdf|, step), voxel) * 0.8 along the optical
// axis, elsewhere by one voxel inside an allocated block and by half a block outside one. A
// sign change from + to - is the surface (linear interpolation of the crossing); from - to +
// it is a surface seen from behind, and the ray stops. Blocks are found through an
// open-addressing hash table that the host builds from its block map (linear probing, empty
// entries have slot -1), so the kernel needs no atomics.

// Host mirror: `CastUniform` in src/tsdf/raycast.rs (a test compares the layouts).
struct Params {
    rot0: vec4<f32>,          // world_from_camera rows, camera centre (m) in w
    rot1: vec4<f32>,
    rot2: vec4<f32>,
    width: u32,               // image size, pixels
    height: u32,
    table_mask: u32,          // hash table entries - 1 (a power of two minus one)
    with_normals: u32,        // 1: write normals
    fx: f32,                  // intrinsics, pixels
    fy: f32,
    cx: f32,
    cy: f32,
    voxel_size: f32,          // m
    step: f32,                // largest march step in free space, m
    min_depth: f32,           // searched depth range along the optical axis, m
    max_depth: f32,
}

// Host mirror: `Voxel` in src/tsdf/integrate.rs.
struct Voxel {
    tsdf: f32,                // m, positive in front of the surface
    weight: f32,
    rgb: u32,                 // 0x00BBGGRR
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> table: array<vec4<i32>>;
@group(0) @binding(2) var<storage, read> voxels: array<Voxel>;
@group(0) @binding(3) var<storage, read_write> out_depth: array<f32>;
@group(0) @binding(4) var<storage, read_write> out_rgb: array<u32>;
@group(0) @binding(5) var<storage, read_write> out_normal: array<vec4<f32>>;

const BLOCK_SIDE: i32 = 8;
const BLOCK_VOXELS: i32 = 512;

// Floor division and remainder by the block side (arithmetic shift: floor for negatives).
fn block_of(g: vec3<i32>) -> vec3<i32> {
    return g >> vec3<u32>(3u);
}

struct Sample {
    ok: bool,
    // tsdf (m), then R, G, B (0-255) when colour was asked for.
    acc: vec4<f32>,
}

// Trilinear interpolation over the 8 voxels around world point p (m); not ok when one of them
// is unallocated or unobserved.
fn trilinear(p: vec3<f32>, colour: bool) -> Sample {
    var out: Sample;
    out.ok = false;
    out.acc = vec4<f32>(0.0);
    let s = params.voxel_size;
    let q = vec3<f32>(p.x / s, p.y / s, p.z / s);
    let b = floor(q);
    let f = vec3<f32>(q.x - b.x, q.y - b.y, q.z - b.z);
    let g = vec3<i32>(b);
    let home = block_of(g);
    let home_slot = find_slot(home);
    var acc = vec4<f32>(0.0);
    for (var c = 0; c < 8; c++) {
        let o = vec3<i32>(c & 1, (c >> 1u) & 1, (c >> 2u) & 1);
        let gc = g + o;
        let bc = block_of(gc);
        var slot = home_slot;
        if (any(bc != home)) {
            slot = find_slot(bc);
        }
        if (slot < 0) {
            return out;
        }
        let l = gc & vec3<i32>(BLOCK_SIDE - 1);
        let v = voxels[slot * BLOCK_VOXELS + l.x + BLOCK_SIDE * (l.y + BLOCK_SIDE * l.z)];
        if (!(v.weight > 0.0)) {
            return out;
        }
        var w = 1.0;
        w = w * select(1.0 - f.x, f.x, o.x == 1);
        w = w * select(1.0 - f.y, f.y, o.y == 1);
        w = w * select(1.0 - f.z, f.z, o.z == 1);
        acc.x = acc.x + w * v.tsdf;
        if (colour) {
            acc.y = acc.y + w * f32(v.rgb & 255u);
            acc.z = acc.z + w * f32((v.rgb >> 8u) & 255u);
            acc.w = acc.w + w * f32((v.rgb >> 16u) & 255u);
        }
    }
    out.ok = true;
    out.acc = acc;
    return out;
}

fn ray_point(ray: vec3<f32>, z: f32) -> vec3<f32> {
    return vec3<f32>(
        params.rot0.w + ray.x * z,
        params.rot1.w + ray.y * z,
        params.rot2.w + ray.z * z,
    );
}

// Unit normal in the camera frame facing the camera from central TSDF differences; zero
// when a difference needs an undefined sample.
fn surface_normal(p: vec3<f32>, ray_c: vec3<f32>) -> vec3<f32> {
    var g = vec3<f32>(0.0);
    for (var k = 0; k < 3; k++) {
        var a = p;
        var b = p;
        a[k] = a[k] + params.voxel_size;
        b[k] = b[k] - params.voxel_size;
        let sa = trilinear(a, false);
        let sb = trilinear(b, false);
        if (!sa.ok || !sb.ok) {
            return vec3<f32>(0.0);
        }
        g[k] = sa.acc.x - sb.acc.x;
    }
    // World to camera: the transpose of world_from_camera's rotation.
    let c = vec3<f32>(
        params.rot0.x * g.x + params.rot1.x * g.y + params.rot2.x * g.z,
        params.rot0.y * g.x + params.rot1.y * g.y + params.rot2.y * g.z,
        params.rot0.z * g.x + params.rot1.z * g.y + params.rot2.z * g.z,
    );
    let l = sqrt(c.x * c.x + c.y * c.y + c.z * c.z);
    if (!(l > 0.0)) {
        return vec3<f32>(0.0);
    }
    var n = vec3<f32>(c.x / l, c.y / l, c.z / l);
    if (n.x * ray_c.x + n.y * ray_c.y + n.z * ray_c.z > 0.0) {
        n = -n;
    }
    return n;
}

@compute @workgroup_size(8, 8, 1)
fn cast_rays(@builtin(global_invocation_id) gid: vec3<u32>) {
    if (gid.x >= params.width || gid.y >= params.height) {
        return;
    }
    let i = gid.y * params.width + gid.x;
    let ray_c = vec3<f32>(
        (f32(gid.x) - params.cx) / params.fx,
        (f32(gid.y) - params.cy) / params.fy,
        1.0,
    );
    let ray = vec3<f32>(
        params.rot0.x * ray_c.x + params.rot0.y * ray_c.y + params.rot0.z * ray_c.z,
        params.rot1.x * ray_c.x + params.rot1.y * ray_c.y + params.rot1.z * ray_c.z,
        params.rot2.x * ray_c.x + params.rot2.y * ray_c.y + params.rot2.z * ray_c.z,
    );
    let len = sqrt(ray_c.x * ray_c.x + ray_c.y * ray_c.y + 1.0);
    let voxel = params.voxel_size;
    let block = voxel * f32(BLOCK_SIDE);
    var depth = 0.0;
    var rgb = 0u;
    var normal = vec3<f32>(0.0);
    var z = params.min_depth;
    var has_prev = false;
    var zp = 0.0;
    var sp = 0.0;
    while (z < params.max_depth) {
        let smp = trilinear(ray_point(ray, z), false);
        if (!smp.ok) {
            has_prev = false;
            // Unknown space: skip faster where the whole block is missing.
            let p = ray_point(ray, z);
            let gp = vec3<i32>(floor(vec3<f32>(p.x / voxel, p.y / voxel, p.z / voxel)));
            var dz = 0.5 * block;
            if (find_slot(block_of(gp)) >= 0) {
                dz = voxel;
            }
            z = z + dz / len;
            continue;
        }
        let s = smp.acc.x;
        if (has_prev) {
            if (sp > 0.0 && s <= 0.0) {
                let zh = zp + (z - zp) * sp / (sp - s);
                depth = zh;
                let ph = ray_point(ray, zh);
                if (params.with_normals == 1u) {
                    normal = surface_normal(ph, ray_c);
                }
                let c = trilinear(ph, true);
                if (c.ok) {
                    let r = u32(clamp(floor(c.acc.y + 0.5), 0.0, 255.0));
                    let gg = u32(clamp(floor(c.acc.z + 0.5), 0.0, 255.0));
                    let bb = u32(clamp(floor(c.acc.w + 0.5), 0.0, 255.0));
                    rgb = r | (gg << 8u) | (bb << 16u);
                }
                break;
            }
            if (sp < 0.0 && s > 0.0) {
                // Seen from behind: not a surface facing this camera.
                break;
            }
        }
        has_prev = true;
        zp = z;
        sp = s;
        z = z + max(min(abs(s), params.step), voxel) * 0.8 / len;
    }
    out_depth[i] = depth;
    out_rgb[i] = rgb;
    if (params.with_normals == 1u) {
        out_normal[i] = vec4<f32>(normal, 0.0);
    }
}
