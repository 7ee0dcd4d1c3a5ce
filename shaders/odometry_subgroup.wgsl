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
        partials[wid.x * nsg + sid] = to_partial(a0, a1, a2, a3, a4, a5, a6, a7);
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
        counts[wid.x * nsg + sid] = c;
    }
}
