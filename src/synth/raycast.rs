//! CPU mirror of `shaders/raycast.wgsl`: the packed (f32) scene layout, procedural textures,
//! ray-primitive intersection, BVH traversal and shading.
//!
//! Every function here has a WGSL twin with the same formulas in the same order, so that the
//! GPU and CPU ray casters agree to f32 rounding (see the parity test). The world frame of
//! the scene has z up; everything is in metres.

use bytemuck::{Pod, Zeroable};

/// Primitive kinds in [`PackedPrim::center`]`[3]`.
pub const KIND_BOX: u32 = 0;
/// A sphere.
pub const KIND_SPHERE: u32 = 1;
/// A capped cylinder along the local z axis.
pub const KIND_CYLINDER: u32 = 2;

/// Object id written for rays that hit nothing.
pub const NO_OBJECT: u32 = u32::MAX;

/// One primitive as the kernels read it (6 x `vec4<f32>`).
#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable, PartialEq)]
pub struct PackedPrim {
    /// Centre in world coordinates; `[3]` holds the kind (bit-cast u32).
    pub center: [f32; 4],
    /// Rows of `local_from_world` rotation, each with one shape parameter in `[3]`:
    /// box half extents (x, y, z); sphere radius in `rows[0][3]`; cylinder radius in
    /// `rows[0][3]` and half height in `rows[1][3]`.
    pub rows: [[f32; 4]; 3],
    /// Texture-space offset added to local coordinates (world-anchored textures for static
    /// structure), `[3]` = material index (bit-cast u32).
    pub anchor: [f32; 4],
    /// `[0]` = object id (bit-cast u32), the rest zero.
    pub extra: [f32; 4],
}

/// One BVH node (2 x `vec4<f32>`): AABB and either two children (`a` = left child index, right
/// child is `a + 1`, `count = 0`) or a leaf of `count` primitives starting at `a`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable, PartialEq)]
pub struct PackedNode {
    /// AABB minimum; `[3]` = `a` (bit-cast u32).
    pub min: [f32; 4],
    /// AABB maximum; `[3]` = `count` (bit-cast u32).
    pub max: [f32; 4],
}

/// One material (3 x `vec4<f32>`): two albedo colours mixed by a procedural pattern.
#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable, PartialEq)]
pub struct PackedMaterial {
    /// Albedo where the pattern is 0 (linear RGB in `[0, 1]`); `[3]` = pattern kind (bit-cast u32).
    pub color0: [f32; 4],
    /// Albedo where the pattern is 1; `[3]` = pattern scale in metres.
    pub color1: [f32; 4],
    /// `[0]` = texture seed (bit-cast u32), `[1]` = specular strength, `[2]` = fine-noise weight.
    pub params: [f32; 4],
}

/// Pattern kinds of [`PackedMaterial`].
pub mod pattern {
    /// Fractal value noise.
    pub const NOISE: u32 = 0;
    /// Wobbly stripes.
    pub const STRIPES: u32 = 1;
    /// Checkerboard (tiles).
    pub const CHECKER: u32 = 2;
    /// "Posters": a grid of cells, each with a random disc or square.
    pub const POSTER: u32 = 3;
    /// Wood-like stretched grain.
    pub const GRAIN: u32 = 4;
}

/// Lighting shared by all pixels of a scene.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Lighting {
    /// Unit direction towards the light, world frame.
    pub to_light: [f32; 3],
    /// Ambient term.
    pub ambient: f32,
    /// Diffuse (Lambert) weight.
    pub diffuse: f32,
}

/// What the ray caster produces for one pixel, before the sensor model.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CastSample {
    /// Depth along the camera z axis, metres (0 when nothing was hit or z <= 0).
    pub z: f32,
    /// |cos| of the angle between the ray and the surface normal (0 when nothing was hit).
    pub cos_incidence: f32,
    /// Shaded colour, linear, nominally in `[0, 1]`.
    pub rgb: [f32; 3],
    /// Object id hit, [`NO_OBJECT`] for none.
    pub object: u32,
}

impl CastSample {
    /// A ray that hit nothing.
    pub const MISS: CastSample = CastSample {
        z: 0.0,
        cos_incidence: 0.0,
        rgb: [0.0; 3],
        object: NO_OBJECT,
    };
}

#[inline]
fn bits(x: f32) -> u32 {
    x.to_bits()
}

/// PCG hash (one round), as in the shader.
#[inline]
pub fn pcg_hash(v: u32) -> u32 {
    let state = v.wrapping_mul(747_796_405).wrapping_add(2_891_336_453);
    let word = ((state >> ((state >> 28) + 4)) ^ state).wrapping_mul(277_803_737);
    (word >> 22) ^ word
}

/// Hash of an integer lattice point and a seed.
#[inline]
pub fn hash2(ix: i32, iy: i32, seed: u32) -> u32 {
    pcg_hash((ix as u32).wrapping_add(pcg_hash((iy as u32).wrapping_add(pcg_hash(seed)))))
}

/// A hash as a float in `[0, 1)`.
#[inline]
pub fn unit(h: u32) -> f32 {
    (h >> 8) as f32 * (1.0 / 16_777_216.0)
}

/// 2-D value noise in `[0, 1]` with smoothstep interpolation.
pub fn value_noise(px: f32, py: f32, seed: u32) -> f32 {
    let fx0 = px.floor();
    let fy0 = py.floor();
    let fx = px - fx0;
    let fy = py - fy0;
    let ix = fx0 as i32;
    let iy = fy0 as i32;
    let a = unit(hash2(ix, iy, seed));
    let b = unit(hash2(ix + 1, iy, seed));
    let c = unit(hash2(ix, iy + 1, seed));
    let d = unit(hash2(ix + 1, iy + 1, seed));
    let ux = fx * fx * (3.0 - 2.0 * fx);
    let uy = fy * fy * (3.0 - 2.0 * fy);
    let ab = a + (b - a) * ux;
    let cd = c + (d - c) * ux;
    ab + (cd - ab) * uy
}

/// Three-octave fractal value noise in `[0, 1]`.
pub fn fbm(px: f32, py: f32, seed: u32) -> f32 {
    let n0 = value_noise(px, py, seed);
    let n1 = value_noise(px * 2.03, py * 2.03, seed + 1);
    let n2 = value_noise(px * 4.11, py * 4.11, seed + 2);
    (0.5 * n0 + 0.3 * n1 + 0.2 * n2 - 0.5) * 1.6 + 0.5
}

/// The pattern value in `[0, 1]` of material `m` at texture coordinates `(u, v)` (metres).
pub fn pattern_value(m: &PackedMaterial, u: f32, v: f32) -> f32 {
    let kind = bits(m.color0[3]);
    let scale = m.color1[3];
    let seed = bits(m.params[0]);
    let su = u / scale;
    let sv = v / scale;
    let p = match kind {
        pattern::STRIPES => {
            let w = fbm(su * 0.5, sv * 0.5, seed + 11);
            0.5 + 0.5 * (6.283_185_5 * su + 3.0 * w).sin()
        }
        pattern::CHECKER => {
            let c = (su.floor() + sv.floor()) as i32;
            if c & 1 == 0 {
                0.15
            } else {
                0.85
            }
        }
        pattern::POSTER => {
            let cx = su.floor();
            let cy = sv.floor();
            let h = hash2(cx as i32, cy as i32, seed + 23);
            let ox = su - cx - (0.3 + 0.4 * unit(pcg_hash(h)));
            let oy = sv - cy - (0.3 + 0.4 * unit(pcg_hash(h + 1)));
            let r = 0.12 + 0.2 * unit(pcg_hash(h + 2));
            let inside = if h & 1 == 0 {
                ox * ox + oy * oy < r * r
            } else {
                ox.abs() < r && oy.abs() < r
            };
            if inside {
                unit(pcg_hash(h + 3))
            } else {
                0.2 + 0.6 * unit(pcg_hash(h + 4)) * 0.5
            }
        }
        pattern::GRAIN => fbm(su * 0.15, sv * 3.0, seed + 31),
        _ => fbm(su, sv, seed + 41),
    };
    let fine = fbm(u * 9.0, v * 9.0, seed + 53);
    let wf = m.params[2];
    let t = p * (1.0 - wf) + fine * wf;
    t.clamp(0.0, 1.0)
}

/// Result of intersecting one primitive: distance, local normal axis info and texture coords.
#[derive(Clone, Copy, Debug)]
struct Hit {
    t: f32,
    normal: [f32; 3],
    u: f32,
    v: f32,
}

#[inline]
fn safe_inv(d: f32) -> f32 {
    if d.abs() < 1e-12 {
        if d < 0.0 {
            -1e12
        } else {
            1e12
        }
    } else {
        1.0 / d
    }
}

#[inline]
fn dot3(a: [f32; 3], b: [f32; 3]) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

#[inline]
fn row(p: &PackedPrim, i: usize) -> [f32; 3] {
    [p.rows[i][0], p.rows[i][1], p.rows[i][2]]
}

/// Intersects the ray `o + t d` (world frame, `d` unit) with primitive `p` for `t` in
/// `(t_min, t_max)`.
fn intersect_prim(p: &PackedPrim, o: [f32; 3], d: [f32; 3], t_min: f32, t_max: f32) -> Option<Hit> {
    let rel = [o[0] - p.center[0], o[1] - p.center[1], o[2] - p.center[2]];
    let r0 = row(p, 0);
    let r1 = row(p, 1);
    let r2 = row(p, 2);
    let lo = [dot3(r0, rel), dot3(r1, rel), dot3(r2, rel)];
    let ld = [dot3(r0, d), dot3(r1, d), dot3(r2, d)];
    let kind = bits(p.center[3]);
    let mut hit_t = -1.0f32;
    let mut ln = [0.0f32; 3];
    if kind == KIND_BOX {
        let h = [p.rows[0][3], p.rows[1][3], p.rows[2][3]];
        let mut t_near = -1e30f32;
        let mut t_far = 1e30f32;
        let mut axis = 0usize;
        for k in 0..3 {
            let inv = safe_inv(ld[k]);
            let ta = (-h[k] - lo[k]) * inv;
            let tb = (h[k] - lo[k]) * inv;
            let t0 = ta.min(tb);
            let t1 = ta.max(tb);
            if t0 > t_near {
                t_near = t0;
                axis = k;
            }
            t_far = t_far.min(t1);
        }
        if t_near <= t_far && t_near > t_min && t_near < t_max {
            hit_t = t_near;
            ln[axis] = if ld[axis] > 0.0 { -1.0 } else { 1.0 };
        }
    } else if kind == KIND_SPHERE {
        let r = p.rows[0][3];
        let b = dot3(lo, ld);
        let c = dot3(lo, lo) - r * r;
        let disc = b * b - c;
        if disc >= 0.0 {
            let t = -b - disc.sqrt();
            if t > t_min && t < t_max {
                hit_t = t;
                let q = [lo[0] + t * ld[0], lo[1] + t * ld[1], lo[2] + t * ld[2]];
                ln = [q[0] / r, q[1] / r, q[2] / r];
            }
        }
    } else {
        let r = p.rows[0][3];
        let hh = p.rows[1][3];
        let a = ld[0] * ld[0] + ld[1] * ld[1];
        let b = lo[0] * ld[0] + lo[1] * ld[1];
        let c = lo[0] * lo[0] + lo[1] * lo[1] - r * r;
        let disc = b * b - a * c;
        if a > 1e-12 && disc >= 0.0 {
            let t = (-b - disc.sqrt()) / a;
            let z = lo[2] + t * ld[2];
            if t > t_min && t < t_max && z.abs() <= hh {
                hit_t = t;
                ln = [(lo[0] + t * ld[0]) / r, (lo[1] + t * ld[1]) / r, 0.0];
            }
        }
        // Caps.
        let inv = safe_inv(ld[2]);
        let cap = if ld[2] > 0.0 { -hh } else { hh };
        let t = (cap - lo[2]) * inv;
        let x = lo[0] + t * ld[0];
        let y = lo[1] + t * ld[1];
        let best = if hit_t > 0.0 { hit_t } else { t_max };
        if t > t_min && t < best && x * x + y * y <= r * r {
            hit_t = t;
            ln = [0.0, 0.0, if ld[2] > 0.0 { -1.0 } else { 1.0 }];
        }
    }
    if hit_t <= 0.0 {
        return None;
    }
    let q = [
        lo[0] + hit_t * ld[0],
        lo[1] + hit_t * ld[1],
        lo[2] + hit_t * ld[2],
    ];
    // Texture coordinates: the two coordinates across the dominant normal axis (plus the
    // anchor), so planar faces get undistorted textures; curved sides use a slanted pair.
    let an = [ln[0].abs(), ln[1].abs(), ln[2].abs()];
    let a = [q[0] + p.anchor[0], q[1] + p.anchor[1], q[2] + p.anchor[2]];
    let (u, v) = if kind == KIND_BOX {
        if an[0] >= an[1] && an[0] >= an[2] {
            (a[1], a[2] + 17.0)
        } else if an[1] >= an[2] {
            (a[0], a[2] + 31.0)
        } else {
            (a[0] + 7.0, a[1])
        }
    } else if kind == KIND_CYLINDER && an[2] < 0.5 {
        (q[1].atan2(q[0]) * p.rows[0][3] + p.anchor[0], a[2])
    } else {
        (a[0] + 0.6 * a[2], a[1] - 0.4 * a[2])
    };
    // Normal back to world: world = R^T * local.
    let n = [
        r0[0] * ln[0] + r1[0] * ln[1] + r2[0] * ln[2],
        r0[1] * ln[0] + r1[1] * ln[1] + r2[1] * ln[2],
        r0[2] * ln[0] + r1[2] * ln[1] + r2[2] * ln[2],
    ];
    Some(Hit {
        t: hit_t,
        normal: n,
        u,
        v,
    })
}

/// Slab test of a node's AABB against the ray; returns the entry distance if it is below `t_max`.
#[inline]
fn node_entry(n: &PackedNode, o: [f32; 3], inv_d: [f32; 3], t_max: f32) -> Option<f32> {
    let mut t0 = 0.0f32;
    let mut t1 = t_max;
    for k in 0..3 {
        let ta = (n.min[k] - o[k]) * inv_d[k];
        let tb = (n.max[k] - o[k]) * inv_d[k];
        t0 = t0.max(ta.min(tb));
        t1 = t1.min(ta.max(tb));
    }
    (t0 <= t1).then_some(t0)
}

/// Maximum BVH depth the traversal stack supports (the builder guarantees it).
pub const MAX_STACK: usize = 32;

/// The packed scene the ray casters read.
#[derive(Clone, Debug, Default)]
pub struct PackedScene {
    /// Primitives in BVH leaf order.
    pub prims: Vec<PackedPrim>,
    /// BVH nodes, root at 0.
    pub nodes: Vec<PackedNode>,
    /// Materials.
    pub materials: Vec<PackedMaterial>,
}

/// Casts one ray (world frame, `d` unit) and shades the hit. `dz` is the ray direction's
/// camera-frame z component (to turn distance into depth).
pub fn cast_ray(
    scene: &PackedScene,
    light: &Lighting,
    o: [f32; 3],
    d: [f32; 3],
    dz: f32,
) -> CastSample {
    if scene.nodes.is_empty() {
        return CastSample::MISS;
    }
    let inv_d = [safe_inv(d[0]), safe_inv(d[1]), safe_inv(d[2])];
    let mut best_t = 1e30f32;
    let mut best: Option<(Hit, usize)> = None;
    let mut stack = [0u32; MAX_STACK];
    let mut sp = 0usize;
    let mut node = 0u32;
    if node_entry(&scene.nodes[0], o, inv_d, best_t).is_none() {
        return CastSample::MISS;
    }
    loop {
        let n = &scene.nodes[node as usize];
        let a = bits(n.min[3]);
        let count = bits(n.max[3]);
        let mut next: Option<u32> = None;
        if count > 0 {
            for i in a..a + count {
                if let Some(h) = intersect_prim(&scene.prims[i as usize], o, d, 1e-4, best_t) {
                    best_t = h.t;
                    best = Some((h, i as usize));
                }
            }
        } else {
            let el = node_entry(&scene.nodes[a as usize], o, inv_d, best_t);
            let er = node_entry(&scene.nodes[a as usize + 1], o, inv_d, best_t);
            match (el, er) {
                (Some(tl), Some(tr)) => {
                    let (near, far) = if tl <= tr { (a, a + 1) } else { (a + 1, a) };
                    if sp < MAX_STACK {
                        stack[sp] = far;
                        sp += 1;
                    }
                    next = Some(near);
                }
                (Some(_), None) => next = Some(a),
                (None, Some(_)) => next = Some(a + 1),
                (None, None) => {}
            }
        }
        match next {
            Some(nx) => node = nx,
            None => {
                // Pop, skipping nodes that are now farther than the best hit.
                let mut found = false;
                while sp > 0 {
                    sp -= 1;
                    let cand = stack[sp];
                    if node_entry(&scene.nodes[cand as usize], o, inv_d, best_t).is_some() {
                        node = cand;
                        found = true;
                        break;
                    }
                }
                if !found {
                    break;
                }
            }
        }
    }
    let Some((hit, pi)) = best else {
        return CastSample::MISS;
    };
    let prim = &scene.prims[pi];
    let mat = &scene.materials[bits(prim.anchor[3]) as usize];
    let t = pattern_value(mat, hit.u, hit.v);
    let mut nrm = hit.normal;
    let ndv = dot3(nrm, d);
    if ndv > 0.0 {
        nrm = [-nrm[0], -nrm[1], -nrm[2]];
    }
    let cos_i = ndv.abs().min(1.0);
    let l = light.to_light;
    let lambert = dot3(nrm, l).max(0.0);
    // Blinn-Phong half vector between the light and the view direction (-d).
    let hx = l[0] - d[0];
    let hy = l[1] - d[1];
    let hz = l[2] - d[2];
    let hl = (hx * hx + hy * hy + hz * hz).sqrt().max(1e-6);
    let ndh = ((nrm[0] * hx + nrm[1] * hy + nrm[2] * hz) / hl).max(0.0);
    let ndh2 = ndh * ndh;
    let ndh4 = ndh2 * ndh2;
    let ndh8 = ndh4 * ndh4;
    let spec = mat.params[1] * ndh8 * ndh8 * ndh8 * ndh8;
    let shade = light.ambient + light.diffuse * lambert;
    let mut rgb = [0.0f32; 3];
    for (k, c) in rgb.iter_mut().enumerate() {
        let albedo = mat.color0[k] + (mat.color1[k] - mat.color0[k]) * t;
        *c = albedo * shade + spec;
    }
    let z = hit.t * dz;
    CastSample {
        z: if z > 0.0 { z } else { 0.0 },
        cos_incidence: cos_i,
        rgb,
        object: bits(prim.extra[0]),
    }
}
