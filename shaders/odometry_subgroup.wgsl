//! include: common.wgsl
//! include: odometry.wgsl
// Subgroup variants of the two reductions of odometry.wgsl, used when the device has
// `Features::SUBGROUP`. Each subgroup adds its invocations' sums with subgroupAdd and its
// first invocation writes one partial to slot `workgroup * num_subgroups + subgroup_id`: no
// workgroup memory and no barrier (llvmpipe runs kernels with barriers as coroutines, and each
// shared-memory access there is a per-lane loop). The host reserves WG / (minimum subgroup
// size) slots per workgroup and zeroes them first; the partials are summed in f64 on the CPU.

@compute @workgroup_size(128)
fn normal_equations_sg(@builtin(local_invocation_id) lid: vec3<u32>,
                       @builtin(workgroup_id) wid: vec3<u32>,
                       @builtin(num_workgroups) nwg: vec3<u32>,
                       @builtin(subgroup_id) sid: u32,
                       @builtin(num_subgroups) nsg: u32,
                       @builtin(subgroup_invocation_id) sl: u32) {
    let acc = accumulate_pixels(wid.x * WG + lid.x, nwg.x * WG);
    let a0 = subgroupAdd(acc.a0);
    let a1 = subgroupAdd(acc.a1);
    let a2 = subgroupAdd(acc.a2);
    let a3 = subgroupAdd(acc.a3);
    let a4 = subgroupAdd(acc.a4);
    let a5 = subgroupAdd(acc.a5);
    let a6 = subgroupAdd(acc.a6);
    let a7 = subgroupAdd(acc.a7.xy);
    if (sl == 0u) {
        let b = (wid.x * nsg + sid) * NPART;
        out[b] = a0.x; out[b + 1u] = a0.y; out[b + 2u] = a0.z; out[b + 3u] = a0.w;
        out[b + 4u] = a1.x; out[b + 5u] = a1.y; out[b + 6u] = a1.z; out[b + 7u] = a1.w;
        out[b + 8u] = a2.x; out[b + 9u] = a2.y; out[b + 10u] = a2.z; out[b + 11u] = a2.w;
        out[b + 12u] = a3.x; out[b + 13u] = a3.y; out[b + 14u] = a3.z; out[b + 15u] = a3.w;
        out[b + 16u] = a4.x; out[b + 17u] = a4.y; out[b + 18u] = a4.z; out[b + 19u] = a4.w;
        out[b + 20u] = a5.x; out[b + 21u] = a5.y; out[b + 22u] = a5.z; out[b + 23u] = a5.w;
        out[b + 24u] = a6.x; out[b + 25u] = a6.y; out[b + 26u] = a6.z; out[b + 27u] = a6.w;
        out[b + 28u] = a7.x; out[b + 29u] = a7.y;
    }
}

@compute @workgroup_size(128)
fn covisibility_sg(@builtin(local_invocation_id) lid: vec3<u32>,
                   @builtin(workgroup_id) wid: vec3<u32>,
                   @builtin(num_workgroups) nwg: vec3<u32>,
                   @builtin(subgroup_id) sid: u32,
                   @builtin(num_subgroups) nsg: u32,
                   @builtin(subgroup_invocation_id) sl: u32) {
    let c = subgroupAdd(count_covisible(wid.x * WG + lid.x, nwg.x * WG));
    if (sl == 0u) {
        let b = 2u * (wid.x * nsg + sid);
        out[b] = c.x;
        out[b + 1u] = c.y;
    }
}
