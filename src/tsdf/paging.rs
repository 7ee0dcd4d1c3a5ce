//! Where each voxel block lives: a device slot of the integration kernels, or host memory
//! when a device budget pages it out.
//!
//! Blocks keep the index they were allocated with (their *block id*, the order of the block
//! list and of saved files). The kernels address voxels by *slot*; without a budget the slot
//! of a block is its id, so an unbounded volume works exactly as without paging. With a
//! budget of `B` slots, a frame whose blocks are not all resident takes free slots first and
//! then evicts the resident blocks farthest from the camera that the frame does not touch:
//! their voxels are read back into a host store, which is then the only copy, and their
//! slots are reused. A block of the host store that a frame needs again is uploaded into a
//! slot before integration. A frame touching more than `B` blocks is integrated in chunks of
//! at most `B` blocks (each block's update depends only on its own voxels and the frame, so
//! chunks give the same voxels as one pass).

use super::integrate::{TsdfKernels, Voxel};
use super::{TsdfError, BLOCK_VOXELS};

/// Where one block's voxels are.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Place {
    /// In this device slot.
    Device(u32),
    /// At this index (in blocks) of the host store.
    Host(u32),
}

/// Marks of the blocks of the frame being integrated (per block id).
const NOT_IN_FRAME: u8 = 0;
const LATER_CHUNK: u8 = 1;
const THIS_CHUNK: u8 = 2;

/// Paging counters and memory of a volume, for reports.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct PagingStats {
    /// Blocks whose voxels are in device slots now.
    pub resident_blocks: usize,
    /// Blocks whose voxels are held in host memory now (paged out).
    pub host_blocks: usize,
    /// Most blocks resident at once so far.
    pub peak_resident_blocks: usize,
    /// Blocks copied from the device to host memory so far.
    pub page_outs: u64,
    /// Blocks copied from host memory back to the device so far.
    pub page_ins: u64,
}

/// The block-to-slot map with the host store of paged-out blocks.
pub(crate) struct Residency {
    /// Most device slots; `None` = unbounded.
    budget: Option<usize>,
    /// Per block id.
    place: Vec<Place>,
    /// Per slot: the block id held, `u32::MAX` when free.
    slot_block: Vec<u32>,
    free_slots: Vec<u32>,
    /// Voxels of paged-out blocks, [`BLOCK_VOXELS`] per host index.
    host: Vec<Voxel>,
    free_host: Vec<u32>,
    /// Per block id, reset after every chunk (see the `*_CHUNK` marks).
    mark: Vec<u8>,
    /// Slot = block id for every block (true until the first eviction).
    identity: bool,
    stats: PagingStats,
}

const FREE: u32 = u32::MAX;

impl Residency {
    pub(crate) fn new(budget: Option<usize>) -> Self {
        Residency {
            budget,
            place: Vec::new(),
            slot_block: Vec::new(),
            free_slots: Vec::new(),
            host: Vec::new(),
            free_host: Vec::new(),
            mark: Vec::new(),
            identity: true,
            stats: PagingStats::default(),
        }
    }

    /// `blocks` blocks all resident at slots equal to their ids (a loaded volume).
    pub(crate) fn reset_resident(&mut self, blocks: usize) {
        *self = Residency {
            place: (0..blocks as u32).map(Place::Device).collect(),
            slot_block: (0..blocks as u32).collect(),
            mark: vec![NOT_IN_FRAME; blocks],
            ..Residency::new(self.budget)
        };
        self.stats.resident_blocks = blocks;
        self.stats.peak_resident_blocks = blocks;
    }

    /// Device slots in use or free (the storage the kernels need).
    #[cfg(test)]
    pub(crate) fn slots(&self) -> usize {
        self.slot_block.len()
    }

    /// Slot of every block equals its id and no block is on the host.
    pub(crate) fn is_identity(&self) -> bool {
        self.identity
    }

    pub(crate) fn stats(&self) -> PagingStats {
        self.stats
    }

    /// Bytes of the host store (capacity) and the bookkeeping.
    pub(crate) fn host_bytes(&self) -> usize {
        self.host.capacity() * std::mem::size_of::<Voxel>()
            + self.place.capacity() * 8
            + (self.slot_block.capacity() + self.free_slots.capacity() + self.free_host.capacity())
                * 4
            + self.mark.capacity()
    }

    /// Records blocks allocated since the last call (ids `place.len()..blocks`), not resident
    /// yet: they get a slot, zeroed, when a frame first needs them.
    fn grow(&mut self, blocks: usize) {
        while self.place.len() < blocks {
            // A new block has never been on the device; `Host(FREE)` marks "no voxels yet".
            self.place.push(Place::Host(FREE));
            self.mark.push(NOT_IN_FRAME);
        }
    }

    /// The voxels of block `id` when it is held on the host (`None` when resident or never
    /// observed).
    pub(crate) fn host_voxels(&self, id: usize) -> Option<&[Voxel]> {
        match self.place.get(id)? {
            Place::Host(h) if *h != FREE => {
                let h = *h as usize;
                self.host.get(h * BLOCK_VOXELS..(h + 1) * BLOCK_VOXELS)
            }
            _ => None,
        }
    }

    /// The device slot of block `id` when resident.
    pub(crate) fn slot(&self, id: usize) -> Option<u32> {
        match self.place.get(id)? {
            Place::Device(s) => Some(*s),
            Place::Host(_) => None,
        }
    }

    /// Integrates the frame's blocks `active` (`[bx, by, bz, block id]`, `blocks` allocated
    /// in all) in chunks of at most the budget's blocks, in order: each chunk is made
    /// resident, then `run` receives the kernels, the number of slots and the chunk as
    /// `[bx, by, bz, slot]`. `camera` is the camera centre in block edges (world frame);
    /// evictions take the resident blocks farthest from it.
    pub(crate) fn integrate_chunks(
        &mut self,
        blocks: usize,
        active: &[[i32; 4]],
        camera: [f64; 3],
        coords: &[[i32; 3]],
        kernels: &mut dyn TsdfKernels,
        mut run: impl FnMut(&mut dyn TsdfKernels, usize, &[[i32; 4]]) -> Result<(), TsdfError>,
    ) -> Result<(), TsdfError> {
        self.grow(blocks);
        let chunk = self.budget.unwrap_or(usize::MAX).max(1);
        for a in active {
            self.mark[a[3] as usize] = LATER_CHUNK;
        }
        let mut result = Ok(());
        let mut slotted = Vec::with_capacity(active.len().min(chunk));
        for part in active.chunks(chunk) {
            for a in part {
                self.mark[a[3] as usize] = THIS_CHUNK;
            }
            let r = self.make_resident(part, camera, coords, kernels);
            let r = r.and_then(|()| {
                slotted.clear();
                for a in part {
                    match self.place[a[3] as usize] {
                        Place::Device(s) => slotted.push([a[0], a[1], a[2], s as i32]),
                        Place::Host(_) => {
                            return Err(TsdfError::InvalidParameter {
                                name: "device_blocks",
                                why: "a block of the frame is not resident".into(),
                            })
                        }
                    }
                }
                run(kernels, self.slot_block.len(), &slotted)
            });
            for a in part {
                self.mark[a[3] as usize] = NOT_IN_FRAME;
            }
            if let Err(e) = r {
                result = Err(e);
                break;
            }
        }
        for a in active {
            self.mark[a[3] as usize] = NOT_IN_FRAME;
        }
        result
    }

    /// Gives every block of `part` a slot: free slots first, new slots up to the budget, then
    /// evicted ones; uploads host-held voxels and zeroes slots of never-observed blocks.
    fn make_resident(
        &mut self,
        part: &[[i32; 4]],
        camera: [f64; 3],
        coords: &[[i32; 3]],
        kernels: &mut dyn TsdfKernels,
    ) -> Result<(), TsdfError> {
        let missing: Vec<u32> = part
            .iter()
            .map(|a| a[3] as u32)
            .filter(|&id| matches!(self.place[id as usize], Place::Host(_)))
            .collect();
        if missing.is_empty() {
            return Ok(());
        }
        let budget = self.budget.unwrap_or(usize::MAX);
        let available = self.free_slots.len() + budget.saturating_sub(self.slot_block.len());
        if missing.len() > available {
            self.evict(missing.len() - available, camera, coords, kernels)?;
        }
        let mut uploads: Vec<(u32, Vec<Voxel>)> = Vec::new();
        let mut zeroed: Vec<u32> = Vec::new();
        for id in missing {
            let slot = match self.free_slots.pop() {
                Some(s) => s,
                None => {
                    self.slot_block.push(FREE);
                    (self.slot_block.len() - 1) as u32
                }
            };
            if slot != id {
                self.identity = false;
            }
            self.slot_block[slot as usize] = id;
            match std::mem::replace(&mut self.place[id as usize], Place::Device(slot)) {
                Place::Host(FREE) => {
                    // Slots beyond the old storage start zeroed; a reused one is cleared.
                    zeroed.push(slot);
                }
                Place::Host(h) => {
                    let h = h as usize;
                    let v = self.host[h * BLOCK_VOXELS..(h + 1) * BLOCK_VOXELS].to_vec();
                    self.free_host.push(h as u32);
                    self.stats.host_blocks -= 1;
                    self.stats.page_ins += 1;
                    uploads.push((slot, v));
                }
                Place::Device(_) => {}
            }
            self.stats.resident_blocks += 1;
        }
        self.stats.peak_resident_blocks = self
            .stats
            .peak_resident_blocks
            .max(self.stats.resident_blocks);
        kernels.write_slots(self.slot_block.len(), &uploads, &zeroed)
    }

    /// Pages out `n` resident blocks not in the current chunk: those of no chunk of the frame
    /// first, then those of later chunks, each group farthest from `camera` first (ties by
    /// block id, so runs are reproducible).
    fn evict(
        &mut self,
        n: usize,
        camera: [f64; 3],
        coords: &[[i32; 3]],
        kernels: &mut dyn TsdfKernels,
    ) -> Result<(), TsdfError> {
        let mut candidates: Vec<(u8, f64, u32)> = self
            .slot_block
            .iter()
            .filter(|&&id| id != FREE && self.mark[id as usize] != THIS_CHUNK)
            .map(|&id| {
                let c = coords[id as usize];
                let d2: f64 = (0..3)
                    .map(|k| {
                        let d = f64::from(c[k]) + 0.5 - camera[k];
                        d * d
                    })
                    .sum();
                (self.mark[id as usize], d2, id)
            })
            .collect();
        if candidates.len() < n {
            return Err(TsdfError::InvalidParameter {
                name: "device_blocks",
                why: format!("{} blocks to evict, only {} evictable", n, candidates.len()),
            });
        }
        let order = |a: &(u8, f64, u32), b: &(u8, f64, u32)| {
            a.0.cmp(&b.0).then(b.1.total_cmp(&a.1)).then(a.2.cmp(&b.2))
        };
        if n < candidates.len() {
            candidates.select_nth_unstable_by(n, order);
            candidates.truncate(n);
        }
        candidates.sort_unstable_by(order);
        let ids: Vec<u32> = candidates.iter().map(|c| c.2).collect();
        let slots: Vec<u32> = ids
            .iter()
            .filter_map(|&id| self.slot(id as usize))
            .collect();
        let voxels = kernels.read_slots(&slots)?;
        for ((&id, &slot), v) in ids
            .iter()
            .zip(&slots)
            .zip(voxels.chunks_exact(BLOCK_VOXELS))
        {
            let h = match self.free_host.pop() {
                Some(h) => h as usize,
                None => {
                    self.host
                        .resize(self.host.len() + BLOCK_VOXELS, Voxel::default());
                    self.host.len() / BLOCK_VOXELS - 1
                }
            };
            self.host[h * BLOCK_VOXELS..(h + 1) * BLOCK_VOXELS].copy_from_slice(v);
            self.place[id as usize] = Place::Host(h as u32);
            self.slot_block[slot as usize] = FREE;
            self.free_slots.push(slot);
            self.stats.resident_blocks -= 1;
            self.stats.host_blocks += 1;
            self.stats.page_outs += 1;
            self.identity = false;
        }
        // Reuse low slots first, so the used storage stays compact.
        self.free_slots.sort_unstable_by(|a, b| b.cmp(a));
        Ok(())
    }

    /// Changes the budget; when fewer slots are allowed than resident blocks, pages out the
    /// blocks farthest from `camera` (block edges, world) and compacts the slots below the
    /// new budget.
    pub(crate) fn set_budget(
        &mut self,
        budget: Option<usize>,
        camera: [f64; 3],
        coords: &[[i32; 3]],
        kernels: &mut dyn TsdfKernels,
    ) -> Result<(), TsdfError> {
        self.grow(coords.len());
        self.budget = budget;
        let Some(b) = budget else {
            return Ok(());
        };
        if self.stats.resident_blocks > b {
            self.evict(self.stats.resident_blocks - b, camera, coords, kernels)?;
        }
        if self.slot_block.len() > b {
            // Move the resident blocks of slots at or beyond the budget into free slots below it.
            let high: Vec<(u32, u32)> = (b..self.slot_block.len())
                .filter(|&s| self.slot_block[s] != FREE)
                .map(|s| (s as u32, self.slot_block[s]))
                .collect();
            self.free_slots.retain(|&s| (s as usize) < b);
            let from: Vec<u32> = high.iter().map(|h| h.0).collect();
            let voxels = kernels.read_slots(&from)?;
            let mut uploads = Vec::with_capacity(high.len());
            for ((_, id), v) in high.iter().zip(voxels.chunks_exact(BLOCK_VOXELS)) {
                let Some(slot) = self.free_slots.pop() else {
                    return Err(TsdfError::InvalidParameter {
                        name: "device_blocks",
                        why: "no free slot below the budget".into(),
                    });
                };
                self.slot_block[slot as usize] = *id;
                self.place[*id as usize] = Place::Device(slot);
                uploads.push((slot, v.to_vec()));
            }
            self.slot_block.truncate(b);
            self.identity = false;
            kernels.write_slots(b, &uploads, &[])?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::{PagingStats, Residency};
    use crate::tsdf::integrate::{CpuTsdf, TsdfKernels, Voxel};
    use crate::tsdf::BLOCK_VOXELS;

    /// A kernel stand-in that stamps every active slot's first voxel with the block's x key
    /// and counts integrations per block (in the weight), on the CPU store.
    fn stamp(k: &mut dyn TsdfKernels, slots: usize, part: &[[i32; 4]]) {
        let mut v = k.voxels().unwrap_or_else(|e| panic!("{e}")).into_owned();
        v.resize(slots * BLOCK_VOXELS, Voxel::default());
        for a in part {
            let x = &mut v[a[3] as usize * BLOCK_VOXELS];
            x.tsdf = a[0] as f32;
            x.weight += 1.0;
        }
        k.set_voxels(slots, &v).unwrap_or_else(|e| panic!("{e}"));
    }

    fn active(ids: &[u32], coords: &[[i32; 3]]) -> Vec<[i32; 4]> {
        ids.iter()
            .map(|&i| {
                let c = coords[i as usize];
                [c[0], c[1], c[2], i as i32]
            })
            .collect()
    }

    #[test]
    fn paging_evicts_the_farthest_blocks_the_frame_does_not_touch() {
        // Ten blocks along x; the budget holds four.
        let coords: Vec<[i32; 3]> = (0..10).map(|x| [x, 0, 0]).collect();
        let mut res = Residency::new(Some(4));
        let mut k = CpuTsdf::default();
        let frame = |res: &mut Residency, k: &mut CpuTsdf, ids: &[u32], cam_x: f64| {
            let act = active(ids, &coords);
            let mut chunks = Vec::new();
            res.integrate_chunks(10, &act, [cam_x, 0.5, 0.5], &coords, k, |k, slots, part| {
                assert!(slots <= 4, "{slots} slots");
                chunks.push(part.len());
                stamp(k, slots, part);
                Ok(())
            })
            .unwrap_or_else(|e| panic!("{e}"));
            chunks
        };
        assert_eq!(frame(&mut res, &mut k, &[0, 1, 2, 3], 0.0), vec![4]);
        assert!(res.is_identity());
        // The camera near block 9 needs block 4: the farthest resident block (0) goes.
        frame(&mut res, &mut k, &[2, 4], 9.0);
        assert_eq!(res.slot(0), None);
        assert!(res.host_voxels(0).is_some());
        for id in [1, 2, 3, 4] {
            assert!(res.slot(id).is_some(), "block {id} evicted");
        }
        // Camera at block 0: blocks 5 and 6 in; 4 and 3 are farthest, but 3 is in the frame,
        // so 4 and then 1 go (block 2 is in the frame too).
        frame(&mut res, &mut k, &[2, 3, 5, 6], 0.0);
        assert_eq!(res.slot(4), None);
        assert_eq!(res.slot(1), None);
        for id in [2, 3, 5, 6] {
            assert!(res.slot(id).is_some(), "block {id} evicted");
        }
        // Block 0 comes back from the host with its voxels.
        frame(&mut res, &mut k, &[0], 0.0);
        let s = res
            .slot(0)
            .unwrap_or_else(|| panic!("block 0 not resident")) as usize;
        let v = k.voxels().unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(v[s * BLOCK_VOXELS].weight, 2.0);
        assert_eq!(v[s * BLOCK_VOXELS].tsdf, 0.0);
        let st = res.stats();
        assert_eq!(
            st,
            PagingStats {
                resident_blocks: 4,
                host_blocks: 3,
                peak_resident_blocks: 4,
                page_outs: 4,
                page_ins: 1,
            }
        );
        // A frame of nine blocks runs in chunks of at most four, each chunk resident while it
        // is integrated, every block integrated once.
        let all: Vec<u32> = (0..9).collect();
        let chunks = frame(&mut res, &mut k, &all, 4.0);
        assert_eq!(chunks, vec![4, 4, 1]);
        let v = k.voxels().unwrap_or_else(|e| panic!("{e}")).into_owned();
        let weight = |id: usize| match res.slot(id) {
            Some(s) => v[s as usize * BLOCK_VOXELS].weight,
            None => res.host_voxels(id).map_or(0.0, |h| h[0].weight),
        };
        let want = [3.0, 2.0, 4.0, 3.0, 2.0, 2.0, 2.0, 1.0, 1.0];
        for (id, w) in want.iter().enumerate() {
            assert_eq!(weight(id), *w, "block {id}");
        }
        assert!(res.stats().peak_resident_blocks <= 4);
        assert_eq!(res.slots(), 4);
    }
}
