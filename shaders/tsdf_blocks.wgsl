// The TSDF kernels' block lookup in the open-addressing table the host builds
// (`src/tsdf/raycast.rs`, `block_table`: entries `[bx, by, bz, slot]`, linear probing, empty
// entries with slot -1). The including kernel declares `table` and `params.table_mask`.

// The block's slot in `voxels` (in blocks), -1 when it is not allocated (or not resident).
fn find_slot(b: vec3<i32>) -> i32 {
    let h = (u32(b.x) * 73856093u) ^ (u32(b.y) * 19349669u) ^ (u32(b.z) * 83492791u);
    var i = h & params.table_mask;
    for (var k = 0u; k <= params.table_mask; k++) {
        let e = table[i];
        if (e.w < 0) {
            return -1;
        }
        if (e.x == b.x && e.y == b.y && e.z == b.z) {
            return e.w;
        }
        i = (i + 1u) & params.table_mask;
    }
    return -1;
}
