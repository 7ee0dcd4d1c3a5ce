//! include: tsdf_blocks.wgsl
// Marching tetrahedra over the TSDF volume, per voxel cube: which of the cube's six Kuhn
// tetrahedra cross the zero level, the vertices on the crossed edges (position and colour
// interpolated along the edge) and each triangle's orientation.
// CPU mirror: src/tsdf/mesh.rs (`cube_triangles`), same f32 operations in the same order.
//
// Two passes, no atomics. `count_cubes`: one workgroup per block slot, one invocation per row
// of 8 cubes along x, writing the row's triangle counts (0-12 per cube) as 4-bit fields of one
// word. The host sums the counts into each row's first triangle and lists the rows that have
// triangles; `emit_cubes`, one invocation per listed row, writes the triangles there in cube
// order, so the output is in the same order as the mirror's. Sharing vertices between
// triangles (by grid edge) and the normals stay on the host, for both backends. A cube's
// corners in the next block (+x, +y, +z) are found through the open-addressing table of
// `tsdf_cast.wgsl`.

// Host mirror: `MeshUniform` in src/tsdf/mesh.rs (a test compares the layouts).
struct Params {
    table_mask: u32,          // hash table entries - 1 (a power of two minus one)
    blocks: u32,              // block slots `count_cubes` visits
    rows: u32,                // listed rows `emit_cubes` visits
    voxel_size: f32,          // m
}

// Host mirror: `Voxel` in src/tsdf/integrate.rs.
struct Voxel {
    tsdf: f32,                // m, positive in front of the surface
    weight: f32,
    rgb: u32,                 // 0x00BBGGRR
}

// Host mirror: `CubeVertex` in src/tsdf/mesh.rs (a test compares the layouts).
struct CubeVertex {
    position: vec3<f32>,      // world frame, m
    code: u32,                // colour in bits 0-23, the edge's cube corners in 24-26 and 27-29
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> table: array<vec4<i32>>;
// Block coordinates per slot (w unused).
@group(0) @binding(2) var<storage, read> coords: array<vec4<i32>>;
@group(0) @binding(3) var<storage, read> voxels: array<Voxel>;
// Per row of cubes (slot * 64 + y + 8 z): 4 bits per cube, cube x in bits 4x..4x+3.
@group(0) @binding(4) var<storage, read_write> counts: array<u32>;
// Listed rows: (slot * 64 + y + 8 z, index of the row's first triangle in out_vertices / 3).
@group(0) @binding(5) var<storage, read> rows: array<vec2<u32>>;
@group(0) @binding(6) var<storage, read_write> out_vertices: array<CubeVertex>;

const BLOCK_SIDE: i32 = 8;
const BLOCK_VOXELS: i32 = 512;
// Workgroups per dispatch row (the host's `ROW`).
const ROW: u32 = 65535u;

// The corner voxels of the cube being processed.
var<private> cv: array<Voxel, 8>;

// Corner c of a cube: bit 0 = +x, bit 1 = +y, bit 2 = +z.
fn corner(c: u32) -> vec3<i32> {
    return vec3<i32>(i32(c & 1u), i32((c >> 1u) & 1u), i32((c >> 2u) & 1u));
}

// Loads the corner voxels of the cube at global voxel g (in block slot `slot` at block
// coordinates b) into cv; false when one is unallocated or unobserved, or when no corner or
// every corner is inside (no triangles).
fn load_cube(g: vec3<i32>, b: vec3<i32>, slot: i32) -> bool {
    var neg = 0u;
    for (var c = 0u; c < 8u; c++) {
        let gc = g + corner(c);
        let bc = gc >> vec3<u32>(3u);
        var s = slot;
        if (any(bc != b)) {
            s = find_slot(bc);
        }
        if (s < 0) {
            return false;
        }
        let l = gc & vec3<i32>(BLOCK_SIDE - 1);
        let v = voxels[s * BLOCK_VOXELS + l.x + BLOCK_SIDE * (l.y + BLOCK_SIDE * l.z)];
        if (!(v.weight > 0.0)) {
            return false;
        }
        cv[c] = v;
        if (v.tsdf < 0.0) {
            neg = neg + 1u;
        }
    }
    return neg != 0u && neg != 8u;
}

// The four corners of Kuhn tetrahedron k (all share the main diagonal 0-7).
fn tetrahedron(k: u32) -> vec4<u32> {
    switch k {
        case 0u: { return vec4<u32>(0u, 1u, 3u, 7u); }
        case 1u: { return vec4<u32>(0u, 1u, 5u, 7u); }
        case 2u: { return vec4<u32>(0u, 2u, 3u, 7u); }
        case 3u: { return vec4<u32>(0u, 2u, 6u, 7u); }
        case 4u: { return vec4<u32>(0u, 4u, 5u, 7u); }
        default: { return vec4<u32>(0u, 4u, 6u, 7u); }
    }
}

// Triangles a tetrahedron with `inside` corners inside gives.
fn tet_triangles(inside: u32) -> u32 {
    if (inside == 1u || inside == 3u) {
        return 1u;
    }
    if (inside == 2u) {
        return 2u;
    }
    return 0u;
}

// Triangles of the cube in cv.
fn cube_count() -> u32 {
    var n = 0u;
    for (var k = 0u; k < 6u; k++) {
        let t = tetrahedron(k);
        var inside = 0u;
        for (var j = 0u; j < 4u; j++) {
            if (cv[t[j]].tsdf < 0.0) {
                inside = inside + 1u;
            }
        }
        n = n + tet_triangles(inside);
    }
    return n;
}

// Edge from corner a to corner b, the corner with fewer bits first (a Kuhn path adds bits).
fn edge(a: u32, b: u32) -> vec2<u32> {
    return vec2<u32>(min(a, b), max(a, b));
}

// Whether the triangle on edges e0, e1, e2 faces from the inside corners (sum_in of n_in)
// towards the outside ones, in integer arithmetic on the doubled edge midpoints (see
// `faces_outward` in the mirror for why this holds for every crossing).
fn faces_outward(e0: vec2<u32>, e1: vec2<u32>, e2: vec2<u32>, sum_in: vec3<i32>, n_in: i32,
                 sum_out: vec3<i32>, n_out: i32) -> bool {
    let m0 = corner(e0.x) + corner(e0.y);
    let m1 = corner(e1.x) + corner(e1.y);
    let m2 = corner(e2.x) + corner(e2.y);
    let u = m1 - m0;
    let w = m2 - m0;
    let n = vec3<i32>(u.y * w.z - u.z * w.y, u.z * w.x - u.x * w.z, u.x * w.y - u.y * w.x);
    let o = sum_out * n_in - sum_in * n_out;
    return n.x * o.x + n.y * o.y + n.z * o.z > 0;
}

fn unpack(rgb: u32) -> vec3<f32> {
    return vec3<f32>(f32(rgb & 255u), f32((rgb >> 8u) & 255u), f32((rgb >> 16u) & 255u));
}

// The vertex on edge e (corners of the cube at global voxel g).
fn edge_vertex(g: vec3<i32>, e: vec2<u32>) -> CubeVertex {
    let sa = cv[e.x].tsdf;
    let sb = cv[e.y].tsdf;
    let t = sa / (sa - sb);
    let ca = corner(e.x);
    let d = corner(e.y) - ca;
    let pa = g + ca;
    let s = params.voxel_size;
    var out: CubeVertex;
    out.position = vec3<f32>(
        (f32(pa.x) + t * f32(d.x)) * s,
        (f32(pa.y) + t * f32(d.y)) * s,
        (f32(pa.z) + t * f32(d.z)) * s,
    );
    let ka = unpack(cv[e.x].rgb);
    let kb = unpack(cv[e.y].rgb);
    let r = u32(clamp(floor(ka.x + t * (kb.x - ka.x) + 0.5), 0.0, 255.0));
    let gg = u32(clamp(floor(ka.y + t * (kb.y - ka.y) + 0.5), 0.0, 255.0));
    let bb = u32(clamp(floor(ka.z + t * (kb.z - ka.z) + 0.5), 0.0, 255.0));
    out.code = r | (gg << 8u) | (bb << 16u) | (e.x << 24u) | (e.y << 27u);
    return out;
}

// Writes the triangles of the cube in cv at global voxel g from triangle `first` on; returns
// how many.
fn cube_triangles(g: vec3<i32>, first: u32) -> u32 {
    var n = 0u;
    for (var k = 0u; k < 6u; k++) {
        let t = tetrahedron(k);
        var ins = vec4<u32>(0u);
        var outs = vec4<u32>(0u);
        var n_in = 0u;
        var n_out = 0u;
        var sum_in = vec3<i32>(0);
        var sum_out = vec3<i32>(0);
        for (var j = 0u; j < 4u; j++) {
            let c = t[j];
            if (cv[c].tsdf < 0.0) {
                ins[n_in] = c;
                n_in = n_in + 1u;
                sum_in = sum_in + corner(c);
            } else {
                outs[n_out] = c;
                n_out = n_out + 1u;
                sum_out = sum_out + corner(c);
            }
        }
        let count = tet_triangles(n_in);
        for (var q = 0u; q < count; q++) {
            var e0: vec2<u32>;
            var e1: vec2<u32>;
            var e2: vec2<u32>;
            if (n_in == 1u) {
                e0 = edge(ins.x, outs.x);
                e1 = edge(ins.x, outs.y);
                e2 = edge(ins.x, outs.z);
            } else if (n_in == 3u) {
                e0 = edge(ins.x, outs.x);
                e1 = edge(ins.y, outs.x);
                e2 = edge(ins.z, outs.x);
            } else if (q == 0u) {
                e0 = edge(ins.x, outs.x);
                e1 = edge(ins.x, outs.y);
                e2 = edge(ins.y, outs.y);
            } else {
                e0 = edge(ins.x, outs.x);
                e1 = edge(ins.y, outs.y);
                e2 = edge(ins.y, outs.x);
            }
            if (!faces_outward(e0, e1, e2, sum_in, i32(n_in), sum_out, i32(n_out))) {
                let swap = e1;
                e1 = e2;
                e2 = swap;
            }
            let base = 3u * (first + n);
            out_vertices[base] = edge_vertex(g, e0);
            out_vertices[base + 1u] = edge_vertex(g, e1);
            out_vertices[base + 2u] = edge_vertex(g, e2);
            n = n + 1u;
        }
    }
    return n;
}

// Global voxel of cube x of row `row` (y + 8 z) in the block at b.
fn cube_voxel(b: vec3<i32>, row: u32, x: u32) -> vec3<i32> {
    return b * BLOCK_SIDE + vec3<i32>(i32(x), i32(row & 7u), i32(row >> 3u));
}

@compute @workgroup_size(64, 1, 1)
fn count_cubes(@builtin(workgroup_id) wg: vec3<u32>,
               @builtin(local_invocation_index) row: u32) {
    let slot = wg.x + wg.y * ROW;
    if (slot >= params.blocks) {
        return;
    }
    let b = coords[slot].xyz;
    var packed = 0u;
    for (var x = 0u; x < 8u; x++) {
        if (load_cube(cube_voxel(b, row, x), b, i32(slot))) {
            packed = packed | (cube_count() << (4u * x));
        }
    }
    counts[slot * 64u + row] = packed;
}

@compute @workgroup_size(64, 1, 1)
fn emit_cubes(@builtin(workgroup_id) wg: vec3<u32>,
              @builtin(local_invocation_index) li: u32) {
    let i = (wg.x + wg.y * ROW) * 64u + li;
    if (i >= params.rows) {
        return;
    }
    let r = rows[i];
    let slot = r.x / 64u;
    let row = r.x % 64u;
    let b = coords[slot].xyz;
    var next = r.y;
    for (var x = 0u; x < 8u; x++) {
        if (load_cube(cube_voxel(b, row, x), b, i32(slot))) {
            next = next + cube_triangles(cube_voxel(b, row, x), next);
        }
    }
}
