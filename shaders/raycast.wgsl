// Ray caster of the synthetic scene generator (CPU mirror: src/synth/raycast.rs).
// One invocation per pixel: rotate the pixel's camera-frame ray (from a precomputed table,
// so any central camera model works) into the world, traverse the BVH (near child first,
// explicit stack), intersect boxes / spheres / capped cylinders, evaluate the procedural
// texture and shade (ambient + Lambert + Blinn-Phong). Output: depth along camera z,
// |cos incidence|, linear RGB and the object id. Loops are short per invocation (BVH
// traversal of a few hundred steps), well under llvmpipe's ~65535-iteration limit.

// Host mirror: `RayParams` in src/synth/gpu.rs (a test compares the layouts).
struct Params {
    // Columns of the world_from_camera rotation (xyz) ; w unused.
    rot0: vec4<f32>,
    rot1: vec4<f32>,
    rot2: vec4<f32>,
    // Camera origin in the world (xyz, m); w unused.
    origin: vec4<f32>,
    // Direction towards the light (xyz), ambient (w).
    light: vec4<f32>,
    diffuse: f32,
    width: u32,       // rays per row and rows
    height: u32,
    node_count: u32,  // BVH nodes
};

struct Prim {
    center: vec4<f32>,
    row0: vec4<f32>,
    row1: vec4<f32>,
    row2: vec4<f32>,
    anchor: vec4<f32>,
    extra: vec4<f32>,
};

struct Node {
    bmin: vec4<f32>,
    bmax: vec4<f32>,
};

struct Material {
    color0: vec4<f32>,
    color1: vec4<f32>,
    params: vec4<f32>,
};

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> prims: array<Prim>;
@group(0) @binding(2) var<storage, read> nodes: array<Node>;
@group(0) @binding(3) var<storage, read> materials: array<Material>;
@group(0) @binding(4) var<storage, read> rays: array<vec4<f32>>;
// Per pixel: rgb (linear), object id (bitcast).
@group(0) @binding(5) var<storage, read_write> out_color: array<vec4<f32>>;
// Per pixel: depth z, |cos incidence|.
@group(0) @binding(6) var<storage, read_write> out_depth: array<vec2<f32>>;

const NO_OBJECT: u32 = 0xffffffffu;
const MAX_STACK: u32 = 32u;

fn pcg_hash(v: u32) -> u32 {
    let state = v * 747796405u + 2891336453u;
    let word = ((state >> ((state >> 28u) + 4u)) ^ state) * 277803737u;
    return (word >> 22u) ^ word;
}

fn hash2(ix: i32, iy: i32, seed: u32) -> u32 {
    return pcg_hash(bitcast<u32>(ix) + pcg_hash(bitcast<u32>(iy) + pcg_hash(seed)));
}

fn unit(h: u32) -> f32 {
    return f32(h >> 8u) * (1.0 / 16777216.0);
}

fn value_noise(px: f32, py: f32, seed: u32) -> f32 {
    let fx0 = floor(px);
    let fy0 = floor(py);
    let fx = px - fx0;
    let fy = py - fy0;
    let ix = i32(fx0);
    let iy = i32(fy0);
    let a = unit(hash2(ix, iy, seed));
    let b = unit(hash2(ix + 1, iy, seed));
    let c = unit(hash2(ix, iy + 1, seed));
    let d = unit(hash2(ix + 1, iy + 1, seed));
    let ux = fx * fx * (3.0 - 2.0 * fx);
    let uy = fy * fy * (3.0 - 2.0 * fy);
    let ab = a + (b - a) * ux;
    let cd = c + (d - c) * ux;
    return ab + (cd - ab) * uy;
}

fn fbm(px: f32, py: f32, seed: u32) -> f32 {
    let n0 = value_noise(px, py, seed);
    let n1 = value_noise(px * 2.03, py * 2.03, seed + 1u);
    let n2 = value_noise(px * 4.11, py * 4.11, seed + 2u);
    return (0.5 * n0 + 0.3 * n1 + 0.2 * n2 - 0.5) * 1.6 + 0.5;
}

fn pattern_value(m: Material, u: f32, v: f32) -> f32 {
    let kind = bitcast<u32>(m.color0.w);
    let scale = m.color1.w;
    let seed = bitcast<u32>(m.params.x);
    let su = u / scale;
    let sv = v / scale;
    var p: f32;
    if (kind == 1u) {
        let w = fbm(su * 0.5, sv * 0.5, seed + 11u);
        p = 0.5 + 0.5 * sin(6.2831855 * su + 3.0 * w);
    } else if (kind == 2u) {
        let c = i32(floor(su) + floor(sv));
        if ((c & 1) == 0) {
            p = 0.15;
        } else {
            p = 0.85;
        }
    } else if (kind == 3u) {
        let cx = floor(su);
        let cy = floor(sv);
        let h = hash2(i32(cx), i32(cy), seed + 23u);
        let ox = su - cx - (0.3 + 0.4 * unit(pcg_hash(h)));
        let oy = sv - cy - (0.3 + 0.4 * unit(pcg_hash(h + 1u)));
        let r = 0.12 + 0.2 * unit(pcg_hash(h + 2u));
        var inside: bool;
        if ((h & 1u) == 0u) {
            inside = ox * ox + oy * oy < r * r;
        } else {
            inside = abs(ox) < r && abs(oy) < r;
        }
        if (inside) {
            p = unit(pcg_hash(h + 3u));
        } else {
            p = 0.2 + 0.6 * unit(pcg_hash(h + 4u)) * 0.5;
        }
    } else if (kind == 4u) {
        p = fbm(su * 0.15, sv * 3.0, seed + 31u);
    } else {
        p = fbm(su, sv, seed + 41u);
    }
    let fine = fbm(u * 9.0, v * 9.0, seed + 53u);
    let wf = m.params.z;
    let t = p * (1.0 - wf) + fine * wf;
    return clamp(t, 0.0, 1.0);
}

fn safe_inv(d: f32) -> f32 {
    if (abs(d) < 1e-12) {
        if (d < 0.0) {
            return -1e12;
        }
        return 1e12;
    }
    return 1.0 / d;
}

struct Hit {
    t: f32,
    normal: vec3<f32>,
    u: f32,
    v: f32,
};

// Returns a hit with t < 0 for none.
fn intersect_prim(p: Prim, o: vec3<f32>, d: vec3<f32>, t_min: f32, t_max: f32) -> Hit {
    var res: Hit;
    res.t = -1.0;
    let rel = vec3<f32>(o.x - p.center.x, o.y - p.center.y, o.z - p.center.z);
    let r0 = p.row0.xyz;
    let r1 = p.row1.xyz;
    let r2 = p.row2.xyz;
    let lo = vec3<f32>(dot(r0, rel), dot(r1, rel), dot(r2, rel));
    let ld = vec3<f32>(dot(r0, d), dot(r1, d), dot(r2, d));
    let kind = bitcast<u32>(p.center.w);
    var hit_t = -1.0;
    var ln = vec3<f32>(0.0, 0.0, 0.0);
    if (kind == 0u) {
        let h = vec3<f32>(p.row0.w, p.row1.w, p.row2.w);
        var t_near = -1e30;
        var t_far = 1e30;
        var axis = 0u;
        for (var k = 0u; k < 3u; k = k + 1u) {
            let inv = safe_inv(ld[k]);
            let ta = (-h[k] - lo[k]) * inv;
            let tb = (h[k] - lo[k]) * inv;
            let t0 = min(ta, tb);
            let t1 = max(ta, tb);
            if (t0 > t_near) {
                t_near = t0;
                axis = k;
            }
            t_far = min(t_far, t1);
        }
        if (t_near <= t_far && t_near > t_min && t_near < t_max) {
            hit_t = t_near;
            var s = 1.0;
            if (ld[axis] > 0.0) {
                s = -1.0;
            }
            if (axis == 0u) {
                ln.x = s;
            } else if (axis == 1u) {
                ln.y = s;
            } else {
                ln.z = s;
            }
        }
    } else if (kind == 1u) {
        let r = p.row0.w;
        let b = dot(lo, ld);
        let c = dot(lo, lo) - r * r;
        let disc = b * b - c;
        if (disc >= 0.0) {
            let t = -b - sqrt(disc);
            if (t > t_min && t < t_max) {
                hit_t = t;
                let q = lo + t * ld;
                ln = q / r;
            }
        }
    } else {
        let r = p.row0.w;
        let hh = p.row1.w;
        let a = ld.x * ld.x + ld.y * ld.y;
        let b = lo.x * ld.x + lo.y * ld.y;
        let c = lo.x * lo.x + lo.y * lo.y - r * r;
        let disc = b * b - a * c;
        if (a > 1e-12 && disc >= 0.0) {
            let t = (-b - sqrt(disc)) / a;
            let z = lo.z + t * ld.z;
            if (t > t_min && t < t_max && abs(z) <= hh) {
                hit_t = t;
                ln = vec3<f32>((lo.x + t * ld.x) / r, (lo.y + t * ld.y) / r, 0.0);
            }
        }
        let inv = safe_inv(ld.z);
        var cap = hh;
        if (ld.z > 0.0) {
            cap = -hh;
        }
        let t = (cap - lo.z) * inv;
        let x = lo.x + t * ld.x;
        let y = lo.y + t * ld.y;
        var best = t_max;
        if (hit_t > 0.0) {
            best = hit_t;
        }
        if (t > t_min && t < best && x * x + y * y <= r * r) {
            hit_t = t;
            var s = 1.0;
            if (ld.z > 0.0) {
                s = -1.0;
            }
            ln = vec3<f32>(0.0, 0.0, s);
        }
    }
    if (hit_t <= 0.0) {
        return res;
    }
    let q = lo + hit_t * ld;
    let an = abs(ln);
    let a = q + p.anchor.xyz;
    var u: f32;
    var v: f32;
    if (kind == 0u) {
        if (an.x >= an.y && an.x >= an.z) {
            u = a.y;
            v = a.z + 17.0;
        } else if (an.y >= an.z) {
            u = a.x;
            v = a.z + 31.0;
        } else {
            u = a.x + 7.0;
            v = a.y;
        }
    } else if (kind == 2u && an.z < 0.5) {
        u = atan2(q.y, q.x) * p.row0.w + p.anchor.x;
        v = a.z;
    } else {
        u = a.x + 0.6 * a.z;
        v = a.y - 0.4 * a.z;
    }
    res.t = hit_t;
    res.normal = vec3<f32>(
        r0.x * ln.x + r1.x * ln.y + r2.x * ln.z,
        r0.y * ln.x + r1.y * ln.y + r2.y * ln.z,
        r0.z * ln.x + r1.z * ln.y + r2.z * ln.z,
    );
    res.u = u;
    res.v = v;
    return res;
}

// Entry distance into a node's box, or -1 when the ray misses it before t_max.
fn node_entry(n: Node, o: vec3<f32>, inv_d: vec3<f32>, t_max: f32) -> f32 {
    var t0 = 0.0;
    var t1 = t_max;
    for (var k = 0u; k < 3u; k = k + 1u) {
        let ta = (n.bmin[k] - o[k]) * inv_d[k];
        let tb = (n.bmax[k] - o[k]) * inv_d[k];
        t0 = max(t0, min(ta, tb));
        t1 = min(t1, max(ta, tb));
    }
    if (t0 <= t1) {
        return t0;
    }
    return -1.0;
}

@compute @workgroup_size(64)
fn raycast(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let width = params.width;
    let height = params.height;
    let node_count = params.node_count;
    let i = gid.x + gid.y * nwg.x * 64u;
    if (i >= width * height) {
        return;
    }
    out_color[i] = vec4<f32>(0.0, 0.0, 0.0, bitcast<f32>(NO_OBJECT));
    out_depth[i] = vec2<f32>(0.0, 0.0);
    let c = rays[i];
    if (c.w == 0.0 || node_count == 0u) {
        return;
    }
    let d = vec3<f32>(
        params.rot0.x * c.x + params.rot1.x * c.y + params.rot2.x * c.z,
        params.rot0.y * c.x + params.rot1.y * c.y + params.rot2.y * c.z,
        params.rot0.z * c.x + params.rot1.z * c.y + params.rot2.z * c.z,
    );
    let o = params.origin.xyz;
    let inv_d = vec3<f32>(safe_inv(d.x), safe_inv(d.y), safe_inv(d.z));
    var best_t = 1e30;
    var best_prim = NO_OBJECT;
    var best_hit: Hit;
    var stack: array<u32, 32>;
    var sp = 0u;
    var node = 0u;
    if (node_entry(nodes[0], o, inv_d, best_t) < 0.0) {
        return;
    }
    loop {
        let n = nodes[node];
        let a = bitcast<u32>(n.bmin.w);
        let count = bitcast<u32>(n.bmax.w);
        var has_next = false;
        var next = 0u;
        if (count > 0u) {
            for (var k = a; k < a + count; k = k + 1u) {
                let h = intersect_prim(prims[k], o, d, 1e-4, best_t);
                if (h.t > 0.0) {
                    best_t = h.t;
                    best_prim = k;
                    best_hit = h;
                }
            }
        } else {
            let el = node_entry(nodes[a], o, inv_d, best_t);
            let er = node_entry(nodes[a + 1u], o, inv_d, best_t);
            if (el >= 0.0 && er >= 0.0) {
                var near = a;
                var far = a + 1u;
                if (el > er) {
                    near = a + 1u;
                    far = a;
                }
                if (sp < MAX_STACK) {
                    stack[sp] = far;
                    sp = sp + 1u;
                }
                next = near;
                has_next = true;
            } else if (el >= 0.0) {
                next = a;
                has_next = true;
            } else if (er >= 0.0) {
                next = a + 1u;
                has_next = true;
            }
        }
        if (has_next) {
            node = next;
        } else {
            var found = false;
            loop {
                if (sp == 0u) {
                    break;
                }
                sp = sp - 1u;
                let cand = stack[sp];
                if (node_entry(nodes[cand], o, inv_d, best_t) >= 0.0) {
                    node = cand;
                    found = true;
                    break;
                }
            }
            if (!found) {
                break;
            }
        }
    }
    if (best_prim == NO_OBJECT) {
        return;
    }
    let prim = prims[best_prim];
    let mat = materials[bitcast<u32>(prim.anchor.w)];
    let t = pattern_value(mat, best_hit.u, best_hit.v);
    var nrm = best_hit.normal;
    let ndv = dot(nrm, d);
    if (ndv > 0.0) {
        nrm = -nrm;
    }
    let cos_i = min(abs(ndv), 1.0);
    let l = params.light.xyz;
    let lambert = max(dot(nrm, l), 0.0);
    let hx = l.x - d.x;
    let hy = l.y - d.y;
    let hz = l.z - d.z;
    let hl = max(sqrt(hx * hx + hy * hy + hz * hz), 1e-6);
    let ndh = max((nrm.x * hx + nrm.y * hy + nrm.z * hz) / hl, 0.0);
    let ndh2 = ndh * ndh;
    let ndh4 = ndh2 * ndh2;
    let ndh8 = ndh4 * ndh4;
    let spec = mat.params.y * ndh8 * ndh8 * ndh8 * ndh8;
    let shade = params.light.w + params.diffuse * lambert;
    let albedo = mat.color0.xyz + (mat.color1.xyz - mat.color0.xyz) * t;
    let rgb = albedo * shade + vec3<f32>(spec, spec, spec);
    var z = best_hit.t * c.z;
    if (z <= 0.0) {
        z = 0.0;
    }
    out_color[i] = vec4<f32>(rgb, prim.extra.x);
    out_depth[i] = vec2<f32>(z, cos_i);
}
