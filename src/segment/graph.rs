//! Graph segmentation: convex/concave edge weights (thesis eq. 5.1 / 6.26) and
//! Felzenszwalb-Huttenlocher merging with sorted edges and union-find.

use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Mutex;

use rayon::prelude::*;

/// Label of a vertex/pixel that belongs to no segment (no depth or no normal).
pub const NO_SEGMENT: u32 = u32::MAX;

/// Weight given to an edge across a depth discontinuity: the largest normal-based weight
/// (antiparallel normals), so such edges are only used by the minimum-size pass.
pub const JUMP_WEIGHT: f32 = 2.0;

/// A weighted graph edge between vertices `a < b`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Edge {
    /// Dimensionless dissimilarity in `[0, 2]`.
    pub w: f32,
    /// First vertex.
    pub a: u32,
    /// Second vertex.
    pub b: u32,
}

/// The convex/concave dissimilarity of two surface samples (points in metres, unit normals).
///
/// `d = 1 - n_i . n_j`; the edge is convex when `(p_j - p_i) . n_j > 0` (the surfaces bend
/// away from the viewer, as on an object's outside) and then weighs `d^2`, otherwise
/// (concave, as where an object meets the floor or two walls meet) it weighs `d`. Convex
/// creases thus merge easily and concave creases separate objects.
#[inline]
pub fn convexity_weight(pi: [f32; 3], ni: [f32; 3], pj: [f32; 3], nj: [f32; 3]) -> f32 {
    let d = (1.0 - (ni[0] * nj[0] + ni[1] * nj[1] + ni[2] * nj[2])).max(0.0);
    let conv = (pj[0] - pi[0]) * nj[0] + (pj[1] - pi[1]) * nj[1] + (pj[2] - pi[2]) * nj[2];
    if conv > 0.0 {
        d * d
    } else {
        d
    }
}

/// Union-find with path halving and union by size (ties: the first argument's root wins),
/// holding the merge threshold `Int(C) + k/|C|` of each root. The parent pointers, which
/// every lookup walks, are an array of their own (1.2 MB for 640x480, so they stay in cache);
/// sizes and thresholds are only read at roots.
struct UnionFind {
    parent: Vec<u32>,
    size: Vec<u32>,
    thresh: Vec<f32>,
}

impl UnionFind {
    fn new(n: usize, k: f32) -> Self {
        Self {
            parent: (0..n as u32).collect(),
            size: vec![1; n],
            thresh: vec![k; n],
        }
    }
    #[inline]
    fn find(&mut self, mut x: u32) -> u32 {
        // Path halving (the store is unconditional: cheaper than a mispredicted branch).
        while self.parent[x as usize] != x {
            let p = self.parent[x as usize];
            self.parent[x as usize] = self.parent[p as usize];
            x = self.parent[x as usize];
        }
        x
    }
    /// Joins roots `a` and `b`; returns the new root.
    #[inline]
    fn union(&mut self, a: u32, b: u32) -> u32 {
        let (big, small) = if self.size[a as usize] >= self.size[b as usize] {
            (a, b)
        } else {
            (b, a)
        };
        self.parent[small as usize] = big;
        self.size[big as usize] += self.size[small as usize];
        big
    }
}

/// The radix key of an edge weight: its IEEE bits mapped so that unsigned order is the float
/// total order (the same map as `radsort`): non-negative floats get the sign bit set,
/// negative ones are inverted.
#[inline]
fn weight_key(w: f32) -> u32 {
    let b = w.to_bits();
    if b & 0x8000_0000 != 0 {
        !b
    } else {
        b ^ 0x8000_0000
    }
}

/// Bits of the most significant digit (the first, bucketing pass of [`sort_edges`]).
const TOP_BITS: u32 = 12;
const TOP_BUCKETS: usize = 1 << TOP_BITS;
/// Bits of each of the two lower digits, sorted per bucket from least significant.
const LOW_BITS: u32 = 10;
const LOW_BUCKETS: usize = 1 << LOW_BITS;
const LOW_MASK: u32 = (1 << LOW_BITS) - 1;
/// Below this many edges a comparison sort is faster than a radix pass.
const SMALL_SORT: usize = 96;
const ZERO_EDGE: Edge = Edge { w: 0.0, a: 0, b: 0 };

/// The inverse of [`weight_key`] (bit-exact).
#[inline]
fn key_weight(k: u32) -> f32 {
    f32::from_bits(if k & 0x8000_0000 != 0 {
        k ^ 0x8000_0000
    } else {
        !k
    })
}

/// An item of the radix sort, ordered by a 32-bit key.
trait RadixItem: Copy + Send + Sync {
    /// A filler value.
    const ZERO: Self;
    /// The radix key.
    fn key(&self) -> u32;
}

impl RadixItem for Edge {
    const ZERO: Self = ZERO_EDGE;
    #[inline]
    fn key(&self) -> u32 {
        weight_key(self.w)
    }
}

/// A compact image-graph edge (see [`Tiles`]): the radix key of the weight in the high 32
/// bits, the tag of the edge in the low 32.
impl RadixItem for u64 {
    const ZERO: Self = 0;
    #[inline]
    fn key(&self) -> u32 {
        (*self >> 32) as u32
    }
}

/// The top 12 bits of an item's radix key.
#[inline]
fn top_digit<T: RadixItem>(e: &T) -> usize {
    (e.key() >> (32 - TOP_BITS)) as usize
}

/// Sorts edges by weight, stably: ties keep their input order. [`image_edges`] and
/// [`crate::segment::TriMesh::weighted_edges`] emit edges sorted by `(a, b)`, so the result is
/// the order by `(w, a, b)` and segmentation is deterministic. Weights are ordered as by
/// [`f32::total_cmp`] (negative NaN first, positive NaN last).
///
/// A radix sort on the 32 bits of the weight: one parallel pass groups the edges by the top
/// 12 bits (an eighth of an octave), then each group is sorted, in parallel, by the low 20
/// bits in two least-significant-digit passes of 10 bits while it is hot in cache; passes
/// whose digit is the same for every edge of a group are skipped.
pub fn sort_edges(edges: &mut [Edge]) {
    if edges.len() <= SMALL_SORT {
        edges.sort_by_key(|e| weight_key(e.w));
        return;
    }
    let pieces: Vec<(&[Edge], Vec<u32>)> = edges
        .par_chunks(1 << 15)
        .map(|c| (c, top_histogram(c)))
        .collect();
    let (mut grouped, sizes) = group_by_top_digit(&pieces);
    let mut buckets = Vec::new();
    let mut rest = &mut grouped[..];
    for &c in sizes.iter().filter(|&&c| c > 0) {
        let (b, tail) = rest.split_at_mut(c);
        buckets.push(b);
        rest = tail;
    }
    // Largest first, for load balance.
    buckets.sort_by_key(|b| std::cmp::Reverse(b.len()));
    buckets
        .into_par_iter()
        .with_max_len(1)
        .for_each_init(Vec::new, |scratch, b| sort_bucket(b, scratch));
    edges.copy_from_slice(&grouped);
}

/// Histogram of the top digits of `edges`.
fn top_histogram(edges: &[Edge]) -> Vec<u32> {
    let mut h = vec![0u32; TOP_BUCKETS];
    for e in edges {
        h[top_digit(e)] += 1;
    }
    h
}

/// The edges of `pieces` (each with the histogram of its top digits), grouped by top digit
/// in one buffer, stably (pieces in order); and the size of every group. The pieces scatter
/// in parallel, each into its own part of every group.
fn group_by_top_digit<T: RadixItem, S: AsRef<[T]> + Sync>(
    pieces: &[(S, Vec<u32>)],
) -> (Vec<T>, Vec<usize>) {
    let mut out = Vec::new();
    let sizes = group_by_top_digit_into(pieces, &mut out);
    (out, sizes)
}

/// [`group_by_top_digit`] into `out` (resized to the number of edges; its old contents are
/// overwritten, so a buffer kept from an earlier call is reused without clearing).
fn group_by_top_digit_into<T: RadixItem, S: AsRef<[T]> + Sync>(
    pieces: &[(S, Vec<u32>)],
    out: &mut Vec<T>,
) -> Vec<usize> {
    let mut sizes = vec![0usize; TOP_BUCKETS];
    for (_, h) in pieces {
        for (s, &c) in sizes.iter_mut().zip(h) {
            *s += c as usize;
        }
    }
    out.resize(sizes.iter().sum(), T::ZERO);
    // Every piece's part of every group, in group-major order.
    let mut parts: Vec<Vec<&mut [T]>> = pieces
        .iter()
        .map(|_| Vec::with_capacity(TOP_BUCKETS))
        .collect();
    let mut rest = &mut out[..];
    for k in 0..TOP_BUCKETS {
        for ((_, h), p) in pieces.iter().zip(parts.iter_mut()) {
            let (part, tail) = rest.split_at_mut(h[k] as usize);
            p.push(part);
            rest = tail;
        }
    }
    pieces
        .par_iter()
        .zip(parts.into_par_iter())
        .for_each(|((edges, _), mut parts)| {
            let mut next = vec![0usize; TOP_BUCKETS];
            for e in edges.as_ref() {
                let k = top_digit(e);
                if let Some(slot) = parts[k].get_mut(next[k]) {
                    *slot = *e;
                }
                next[k] += 1;
            }
        });
    sizes
}

/// Sorts a group of edges (sharing the top digit) in place by the low 20 key bits, stably,
/// with `scratch` as the second buffer.
fn sort_bucket<T: RadixItem>(v: &mut [T], scratch: &mut Vec<T>) {
    let n = v.len();
    if n <= SMALL_SORT {
        v.sort_by_key(|e| e.key());
        return;
    }
    let mut h0 = [0u32; LOW_BUCKETS];
    let mut h1 = [0u32; LOW_BUCKETS];
    for e in v.iter() {
        let k = e.key();
        h0[(k & LOW_MASK) as usize] += 1;
        h1[((k >> LOW_BITS) & LOW_MASK) as usize] += 1;
    }
    if scratch.len() < n {
        scratch.resize(n, T::ZERO);
    }
    let tmp = &mut scratch[..n];
    let trivial = |h: &[u32; LOW_BUCKETS]| h.iter().any(|&c| c as usize == n);
    match (trivial(&h0), trivial(&h1)) {
        (true, true) => {}
        (false, true) => {
            scatter(v, tmp, &h0, 0);
            v.copy_from_slice(tmp);
        }
        (true, false) => {
            scatter(v, tmp, &h1, LOW_BITS);
            v.copy_from_slice(tmp);
        }
        (false, false) => {
            scatter(v, tmp, &h0, 0);
            scatter(tmp, v, &h1, LOW_BITS);
        }
    }
}

/// One stable counting-sort pass of `src` into `dst` by the digit at `shift`, whose histogram
/// is `hist`.
fn scatter<T: RadixItem>(src: &[T], dst: &mut [T], hist: &[u32; LOW_BUCKETS], shift: u32) {
    let mut next = [0u32; LOW_BUCKETS];
    let mut sum = 0u32;
    for (o, &c) in next.iter_mut().zip(hist) {
        *o = sum;
        sum += c;
    }
    for e in src {
        let d = ((e.key() >> shift) & LOW_MASK) as usize;
        dst[next[d] as usize] = *e;
        next[d] += 1;
    }
}

/// Sorts the groups (consecutive parts of `grouped` of the given sizes, in increasing top
/// digit) and calls `consume` on each, in order, while later groups are being sorted on
/// another thread (if the pool has one): the union-find pass, which is sequential, starts on
/// the lightest edges before the heavier ones are sorted.
///
/// Groups are claimed in order from a shared counter by a helper task and by the consumer
/// whenever the next group is not sorted yet, so nothing waits on a task that cannot run
/// (a pool of one thread sorts everything on the consumer's thread). `consume(None)` follows
/// the last group, still beside the helper. The helper, once nothing is left to sort, runs
/// `side`: independent work that fills the other core while the sequential union-find and
/// its tail run.
fn for_each_sorted_bucket<T: RadixItem>(
    grouped: &mut [T],
    sizes: &[usize],
    scratch: &mut [Vec<T>; 2],
    mut consume: impl FnMut(Option<&[T]>) + Send,
    side: impl FnOnce() + Send,
) {
    struct Slot<'a, T> {
        edges: &'a mut [T],
        sorted: bool,
    }
    let mut slots = Vec::new();
    let mut rest = grouped;
    for &c in sizes.iter().filter(|&&c| c > 0) {
        let (edges, tail) = rest.split_at_mut(c);
        slots.push(Mutex::new(Slot {
            edges,
            sorted: false,
        }));
        rest = tail;
    }
    let next = AtomicUsize::new(0);
    let claim_and_sort = |scratch: &mut Vec<T>| -> bool {
        let Some(slot) = slots.get(next.fetch_add(1, Ordering::Relaxed)) else {
            return false;
        };
        // A poisoned lock means a sort panicked; that panic leaves the scope below.
        let Ok(mut s) = slot.lock() else {
            return false;
        };
        sort_bucket(s.edges, scratch);
        s.sorted = true;
        true
    };
    let [helper_scratch, own_scratch] = scratch;
    rayon::scope(|sc| {
        sc.spawn(|_| {
            while claim_and_sort(helper_scratch) {}
            side();
        });
        let scratch = own_scratch;
        for slot in &slots {
            loop {
                {
                    let Ok(s) = slot.lock() else {
                        // The helper panicked sorting this group: stop, its panic propagates.
                        return;
                    };
                    if s.sorted {
                        consume(Some(s.edges));
                        break;
                    }
                }
                if !claim_and_sort(scratch) {
                    // Claimed by the helper, which is about to lock and sort it.
                    std::thread::yield_now();
                }
            }
        }
        consume(None);
    });
}

/// Felzenszwalb-Huttenlocher segmentation of a graph with `n` vertices.
///
/// `edges` must be sorted with [`sort_edges`]. Components `C1`, `C2` joined by an edge of
/// weight `w` merge when `w <= min(Int(C1) + k/|C1|, Int(C2) + k/|C2|)`, `Int` being the
/// largest weight of the component's minimum spanning tree. Afterwards, components smaller
/// than `min_size` vertices merge along the remaining edges in weight order. `active[i]` false
/// marks vertices that belong to no segment (they get [`NO_SEGMENT`]). Edges with a vertex
/// `>= n` are ignored.
///
/// Returns one label per vertex, numbered `0..count` in order of first appearance, and `count`.
pub fn felzenszwalb(
    n: usize,
    edges: &[Edge],
    k: f32,
    min_size: usize,
    active: &[bool],
) -> (Vec<u32>, usize) {
    let mut merger = Merger::new(n, k, min_size);
    merger.add(edges);
    merger.finish(active)
}

/// Felzenszwalb-Huttenlocher merging fed with edges in weight order, in pieces.
struct Merger {
    uf: UnionFind,
    n: usize,
    k: f32,
    min_size: usize,
    /// Edges that joined two components, or whose ends were already joined, stay inside one
    /// component for good: only the rejected ones matter to the minimum-size pass, which
    /// visits them in the same (weight) order.
    rejected: Vec<(u32, u32)>,
}

impl Merger {
    fn new(n: usize, k: f32, min_size: usize) -> Self {
        Self {
            uf: UnionFind::new(n, k),
            n,
            k,
            min_size,
            rejected: Vec::new(),
        }
    }

    /// The merging pass over the next edges in weight order.
    fn add(&mut self, edges: &[Edge]) {
        let (n, k) = (self.n, self.k);
        let uf = &mut self.uf;
        for e in edges {
            if e.a as usize >= n || e.b as usize >= n {
                continue;
            }
            let a = uf.find(e.a);
            let b = uf.find(e.b);
            if a == b {
                continue;
            }
            if e.w <= uf.thresh[a as usize] && e.w <= uf.thresh[b as usize] {
                let r = uf.union(a, b) as usize;
                uf.thresh[r] = e.w + k / uf.size[r] as f32;
            } else if self.min_size > 1 {
                self.rejected.push((e.a, e.b));
            }
        }
    }

    /// The minimum-size pass and the labels (see [`felzenszwalb`]).
    fn finish(mut self, active: &[bool]) -> (Vec<u32>, usize) {
        let (uf, min_size, n) = (&mut self.uf, self.min_size, self.n);
        for &(ea, eb) in &self.rejected {
            let a = uf.find(ea);
            let b = uf.find(eb);
            if a != b
                && ((uf.size[a as usize] as usize) < min_size
                    || (uf.size[b as usize] as usize) < min_size)
            {
                uf.union(a, b);
            }
        }
        let mut map = vec![NO_SEGMENT; n];
        let mut labels = vec![NO_SEGMENT; n];
        let mut count = 0u32;
        for (i, label) in labels.iter_mut().enumerate() {
            if !active.get(i).copied().unwrap_or(false) {
                continue;
            }
            let r = uf.find(i as u32) as usize;
            if map[r] == NO_SEGMENT {
                map[r] = count;
                count += 1;
            }
            *label = map[r];
        }
        (labels, count as usize)
    }
}

#[cfg(any(test, feature = "internals"))]
/// Felzenszwalb-Huttenlocher segmentation of the 8-connected image graph: the same labels as
/// [`felzenszwalb`]`(width * height, e, k, min_size, active)` with `e` the edges of
/// [`image_edges`] sorted by [`sort_edges`], computed without the whole sorted edge list:
/// bands of rows emit their edges (8-byte, over pixels numbered in 4x4 tiles) grouped by the
/// top digit of the weight, and the union-find pass consumes the groups as they are sorted,
/// overlapping the sort of the heavier edges. Its buffers (~90 bytes per pixel) are allocated
/// per call: [`segment_image_graph_with`] reuses them.
#[allow(clippy::too_many_arguments)]
pub fn segment_image_graph(
    width: usize,
    height: usize,
    points: &[[f32; 3]],
    normals: &[[f32; 3]],
    inverse_depth: &[f32],
    jump_ratio: f32,
    k: f32,
    min_size: usize,
    active: &[bool],
) -> (Vec<u32>, usize) {
    segment_image_graph_with(
        &mut GraphScratch::default(),
        width,
        height,
        points,
        normals,
        inverse_depth,
        jump_ratio,
        k,
        min_size,
        active,
    )
}

#[cfg(any(test, feature = "internals"))]
/// [`segment_image_graph`] with its buffers in `scratch`, kept there for the next call (the
/// same labels, whatever `scratch` held before).
#[allow(clippy::too_many_arguments)]
pub fn segment_image_graph_with(
    scratch: &mut GraphScratch,
    width: usize,
    height: usize,
    points: &[[f32; 3]],
    normals: &[[f32; 3]],
    inverse_depth: &[f32],
    jump_ratio: f32,
    k: f32,
    min_size: usize,
    active: &[bool],
) -> (Vec<u32>, usize) {
    let inputs = GraphInputs {
        width,
        height,
        points,
        normals,
        inverse_depth,
        jump_ratio,
    };
    segment_image_graph_beside(scratch, &inputs, k, min_size, active, || ()).0
}

/// [`segment_image_graph`], with `side` (work independent of the graph, e.g. the
/// eigen-transform) run on the second core once the edges are sorted, beside the sequential
/// union-find; returns both results. Labels are those of [`segment_image_graph`].
pub(crate) fn segment_image_graph_beside<R: Send + Default>(
    scratch: &mut GraphScratch,
    inputs: &GraphInputs,
    k: f32,
    min_size: usize,
    active: &[bool],
    side: impl FnOnce() -> R + Send,
) -> ((Vec<u32>, usize), R) {
    let (width, height) = (inputs.width, inputs.height);
    let mut side_out = None;
    let run_side = || side_out = Some(side());
    let mut out = (Vec::new(), 0);
    if let Some(tiles) = Tiles::new(width, height) {
        tagged_edge_bands(inputs, &tiles, &mut scratch.bands);
        let sizes = group_by_top_digit_into::<u64, _>(&scratch.bands, &mut scratch.grouped);
        let mut merger = TiledMerger::new(&tiles, k, min_size, scratch);
        let mut labels = None;
        for_each_sorted_bucket(
            &mut scratch.grouped,
            &sizes,
            &mut scratch.sort,
            |b| match b {
                Some(b) => merger.add(b),
                None => labels = Some(merger.finish(width, height, active)),
            },
            run_side,
        );
        merger.give_back(scratch);
        if let Some(l) = labels {
            out = l;
        }
    } else {
        // Too many pixels for the compact edges: the edges of `image_edges`.
        let bands = image_edge_bands(
            width,
            height,
            inputs.points,
            inputs.normals,
            inputs.inverse_depth,
            inputs.jump_ratio,
        );
        let (mut grouped, sizes) = group_by_top_digit(&bands);
        drop(bands);
        let mut merger = Merger::new(width * height, k, min_size);
        let mut scratch = [Vec::new(), Vec::new()];
        let mut merged = false;
        for_each_sorted_bucket(
            &mut grouped,
            &sizes,
            &mut scratch,
            |b| match b {
                Some(b) => merger.add(b),
                None => merged = true,
            },
            run_side,
        );
        if merged {
            out = merger.finish(active);
        }
    }
    // `side` has run on the helper unless that panicked (which propagated above).
    (out, side_out.unwrap_or_default())
}

/// The buffers of the image-graph path of [`segment_image_graph`] (edge bands, the grouped
/// edges, sort scratch, union-find arrays, rejected edges, label map: ~90 bytes per pixel,
/// more once the edge bands have grown for a busier image), for [`segment_image_graph_with`] to reuse, so that the next image of
/// the same size writes memory that is already mapped instead of taking a page fault (the
/// kernel mapping and zeroing a new page) every 4 KiB. Images too large for the compact edges
/// (over 2^30 pixels) do not use it.
#[derive(Default)]
pub struct GraphScratch {
    bands: Vec<(Vec<u64>, Vec<u32>)>,
    grouped: Vec<u64>,
    sort: [Vec<u64>; 2],
    parent: Vec<u32>,
    root: Vec<RootInfo>,
    rejected: Vec<u32>,
    map: Vec<u32>,
}

impl GraphScratch {
    #[cfg(any(test, feature = "internals"))]
    /// Empty buffers (the first image allocates them).
    pub fn new() -> Self {
        Self::default()
    }

    /// Bytes of capacity the buffers hold.
    pub fn bytes(&self) -> usize {
        use super::vec_bytes;
        vec_bytes(&self.bands)
            + self
                .bands
                .iter()
                .map(|(e, t)| vec_bytes(e) + vec_bytes(t))
                .sum::<usize>()
            + vec_bytes(&self.grouped)
            + self.sort.iter().map(vec_bytes).sum::<usize>()
            + vec_bytes(&self.parent)
            + vec_bytes(&self.root)
            + vec_bytes(&self.rejected)
            + vec_bytes(&self.map)
    }
}

impl std::fmt::Debug for GraphScratch {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("GraphScratch")
            .field("bytes", &self.bytes())
            .finish_non_exhaustive()
    }
}

/// Bits of a node number in an edge tag of [`Tiles`]; the two above give the direction.
const NODE_BITS: u32 = 30;
const NODE_MASK: u32 = (1 << NODE_BITS) - 1;

/// The union-find numbering of the pixels of the fused image path: 4 x 4 tiles of 16
/// consecutive nodes, row-major within a tile and tiles row-major, so the two ends of most
/// edges (and the pixels around them) share a cache line of the union-find arrays, where
/// row-major numbering puts the pixel below 64 lines away.
///
/// An edge is tagged `a | dir << 30` by the node `a` of its first pixel (row-major first) and
/// the direction of the second: 0 right, 1 down-left, 2 down, 3 down-right (the order of
/// [`image_edges`]); the second node is `a` plus a delta that depends only on the direction
/// and `a`'s place in its tile.
struct Tiles {
    /// Tiles per row.
    tiles_w: usize,
    /// Number of nodes (the image padded to whole tiles).
    n: usize,
    /// Node delta of the second pixel, at `(place in tile) << 2 | dir`.
    delta: [u32; 64],
}

impl Tiles {
    /// `None` when the padded image has more than `2^30` pixels.
    fn new(width: usize, height: usize) -> Option<Self> {
        let tiles_w = width.div_ceil(4);
        let n = tiles_w.checked_mul(height.div_ceil(4))?.checked_mul(16)?;
        if n > NODE_MASK as usize {
            return None;
        }
        let mut t = Self {
            tiles_w,
            n,
            delta: [0; 64],
        };
        for ly in 0..4 {
            for lx in 0..4 {
                // Any pixel with this place in its tile (and a left neighbour) has the same
                // deltas, padding or not.
                let (x, y) = (4 + lx, ly);
                let a = t.node(x, y);
                let seconds = [(x + 1, y), (x - 1, y + 1), (x, y + 1), (x + 1, y + 1)];
                for (dir, (bx, by)) in seconds.into_iter().enumerate() {
                    t.delta[((ly * 4 + lx) << 2) | dir] = t.node(bx, by).wrapping_sub(a);
                }
            }
        }
        Some(t)
    }

    /// The node of pixel `(x, y)` (wrapping arithmetic: only the deltas use padding pixels
    /// beyond the tiles, which [`Tiles::new`] counts).
    #[inline]
    fn node(&self, x: usize, y: usize) -> u32 {
        ((((y >> 2) * self.tiles_w + (x >> 2)) << 4) | ((y & 3) << 2) | (x & 3)) as u32
    }

    /// The two nodes of an edge tag.
    #[inline]
    fn ends(&self, tag: u32) -> (u32, u32) {
        let a = tag & NODE_MASK;
        let dir = tag >> NODE_BITS;
        let b = a.wrapping_add(self.delta[(((a & 15) << 2) | dir) as usize]);
        (a, b)
    }
}

#[inline(always)]
fn has_normal(v: [f32; 3]) -> bool {
    v[0] != 0.0 || v[1] != 0.0 || v[2] != 0.0
}

/// The edges of [`image_edges`] as compact `u64` ([`RadixItem`]) with [`Tiles`] tags, in
/// bands of [`BAND_ROWS`] rows, in parallel, each with the histogram of its top digits, into
/// `bands` (one entry per band; their buffers are reused). Same weights and order as
/// [`image_edge_bands`]. No edges when the inputs are shorter than the image.
fn tagged_edge_bands(inputs: &GraphInputs, tiles: &Tiles, bands: &mut Vec<(Vec<u64>, Vec<u32>)>) {
    let &GraphInputs {
        width,
        height,
        points,
        normals,
        inverse_depth,
        jump_ratio,
    } = inputs;
    let n = width * height;
    if n == 0 || points.len() < n || normals.len() < n || inverse_depth.len() < n {
        bands.clear();
        return;
    }
    let px = Pixels {
        width,
        height,
        points: &points[..n],
        normals: &normals[..n],
        rho: &inverse_depth[..n],
        // The products of `image_edges` (`jump_ratio * dist` first).
        lim_side: jump_ratio * 1.0,
        lim_diag: jump_ratio * std::f32::consts::SQRT_2,
    };
    bands.resize_with(height.div_ceil(BAND_ROWS), Default::default);
    bands
        .par_iter_mut()
        .enumerate()
        .for_each(|(band, slot)| px.tagged_band(band, tiles, slot));
}

/// The image-graph inputs of [`segment_image_graph`], as given.
pub(crate) struct GraphInputs<'a> {
    pub(crate) width: usize,
    pub(crate) height: usize,
    pub(crate) points: &'a [[f32; 3]],
    pub(crate) normals: &'a [[f32; 3]],
    pub(crate) inverse_depth: &'a [f32],
    pub(crate) jump_ratio: f32,
}

/// The per-pixel inputs of [`tagged_edge_bands`].
struct Pixels<'a> {
    width: usize,
    height: usize,
    points: &'a [[f32; 3]],
    normals: &'a [[f32; 3]],
    rho: &'a [f32],
    lim_side: f32,
    lim_diag: f32,
}

/// One image row of [`Pixels`] as structure of arrays, so the weights of a whole row of
/// edges vectorise: point and normal components, inverse depth, and whether the pixel has a
/// normal (`valid[x + 1]` for pixel `x`; `valid[0]` and `valid[width + 1]` stay false, so
/// the neighbours of the first and last pixel need no bounds test).
#[derive(Default)]
struct RowSoa {
    p: [Vec<f32>; 3],
    n: [Vec<f32>; 3],
    rho: Vec<f32>,
    valid: Vec<bool>,
}

impl RowSoa {
    /// Fills the row with row `y` of `px`, or with no valid pixel when `y` is out of range.
    fn load(&mut self, px: &Pixels, y: usize) {
        let w = px.width;
        self.valid.clear();
        self.valid.resize(w + 2, false);
        if y >= px.height {
            return;
        }
        let r = y * w..(y + 1) * w;
        let (points, normals) = (&px.points[r.clone()], &px.normals[r.clone()]);
        for c in 0..3 {
            self.p[c].clear();
            self.p[c].extend(points.iter().map(|v| v[c]));
            self.n[c].clear();
            self.n[c].extend(normals.iter().map(|v| v[c]));
        }
        self.rho.clear();
        self.rho.extend_from_slice(&px.rho[r]);
        for (v, &nv) in self.valid[1..=w].iter_mut().zip(normals) {
            *v = has_normal(nv);
        }
    }

    /// The columns `range` of the row.
    fn cols(&self, range: std::ops::Range<usize>) -> RowCols<'_> {
        RowCols {
            p: [
                &self.p[0][range.clone()],
                &self.p[1][range.clone()],
                &self.p[2][range.clone()],
            ],
            n: [
                &self.n[0][range.clone()],
                &self.n[1][range.clone()],
                &self.n[2][range.clone()],
            ],
            rho: &self.rho[range],
        }
    }
}

/// Equal-length column slices of a [`RowSoa`].
struct RowCols<'a> {
    p: [&'a [f32]; 3],
    n: [&'a [f32]; 3],
    rho: &'a [f32],
}

/// `out[x]` = the weight of the edge from pixel `x` of `a` to pixel `x` of `b` (all of the
/// same length), `lim` being `jump_ratio` times their distance in pixels: the arithmetic of
/// [`image_edges`] ([`convexity_weight`] or [`JUMP_WEIGHT`]) operation for operation, so the
/// weights are bit-identical, written for the vectoriser (no branch, unit stride).
fn row_weights(out: &mut [f32], a: &RowCols, b: &RowCols, lim: f32) {
    let m = out.len();
    let (ap, an, ar) = (a.p.map(|c| &c[..m]), a.n.map(|c| &c[..m]), &a.rho[..m]);
    let (bp, bn, br) = (b.p.map(|c| &c[..m]), b.n.map(|c| &c[..m]), &b.rho[..m]);
    for x in 0..m {
        let (ri, rj) = (ar[x], br[x]);
        let d = (1.0 - (an[0][x] * bn[0][x] + an[1][x] * bn[1][x] + an[2][x] * bn[2][x])).max(0.0);
        let conv = (bp[0][x] - ap[0][x]) * bn[0][x]
            + (bp[1][x] - ap[1][x]) * bn[1][x]
            + (bp[2][x] - ap[2][x]) * bn[2][x];
        let w = if conv > 0.0 { d * d } else { d };
        out[x] = if (ri - rj).abs() > lim * ri.max(rj) {
            JUMP_WEIGHT
        } else {
            w
        };
    }
}

impl Pixels<'_> {
    /// The tagged edges of one band of rows and the histogram of their top digits, in the
    /// order of [`image_edges`] (by first pixel, then direction: right, down-left, down,
    /// down-right). The weights of each row come from [`row_weights`], one direction at a
    /// time; the emission then writes every candidate edge and advances only past those
    /// whose two pixels have normals (no data-dependent branch). Written into `slot`, whose
    /// buffers are reused: the edge buffer's old contents are overwritten, not cleared.
    fn tagged_band(&self, band: usize, tiles: &Tiles, slot: &mut (Vec<u64>, Vec<u32>)) {
        let (width, height) = (self.width, self.height);
        let rows = band * BAND_ROWS..((band + 1) * BAND_ROWS).min(height);
        let (out, hist) = slot;
        // One spare slot: a rejected candidate is written past the last kept edge.
        out.resize(rows.len() * width * 4 + 1, 0);
        let mut kept = 0usize;
        hist.clear();
        hist.resize(TOP_BUCKETS, 0);
        let (mut cur, mut next) = (RowSoa::default(), RowSoa::default());
        // Weights by direction, indexed by the first pixel's column.
        let mut wts = [
            vec![0f32; width],
            vec![0f32; width],
            vec![0f32; width],
            vec![0f32; width],
        ];
        if width == 0 {
            out.clear();
            return;
        }
        cur.load(self, rows.start);
        for y in rows {
            next.load(self, y + 1);
            let all = cur.cols(0..width);
            row_weights(
                &mut wts[0][..width - 1],
                &all,
                &cur.cols(1..width),
                self.lim_side,
            );
            if y + 1 < height {
                let below = next.cols(0..width);
                row_weights(
                    &mut wts[1][1..],
                    &cur.cols(1..width),
                    &next.cols(0..width - 1),
                    self.lim_diag,
                );
                row_weights(&mut wts[2], &all, &below, self.lim_side);
                row_weights(
                    &mut wts[3][..width - 1],
                    &all,
                    &next.cols(1..width),
                    self.lim_diag,
                );
            }
            let (vc, vn) = (&cur.valid[..width + 2], &next.valid[..width + 2]);
            for x in 0..width {
                let node = u64::from(tiles.node(x, y));
                let here = vc[x + 1];
                // (second pixel valid, weight, direction) in the order of `image_edges`;
                // the next row's flags are all false below the last row.
                let cand = [
                    (vc[x + 2], wts[0][x], 0u64),
                    (vn[x], wts[1][x], 1),
                    (vn[x + 1], wts[2][x], 2),
                    (vn[x + 2], wts[3][x], 3),
                ];
                for (there, w, dir) in cand {
                    let e = (u64::from(weight_key(w)) << 32) | node | dir << NODE_BITS;
                    let ok = here & there;
                    out[kept] = e;
                    hist[top_digit(&e)] += u32::from(ok);
                    kept += usize::from(ok);
                }
            }
            std::mem::swap(&mut cur, &mut next);
        }
        out.truncate(kept);
    }
}

/// Asks the CPU to fetch the cache line of `p` (a hint: any address is allowed).
#[inline(always)]
fn prefetch<T>(p: *const T) {
    #[cfg(target_arch = "x86_64")]
    // SAFETY: a prefetch does not access memory architecturally (it cannot fault), and SSE is
    // part of the x86_64 baseline.
    unsafe {
        core::arch::x86_64::_mm_prefetch::<{ core::arch::x86_64::_MM_HINT_T0 }>(p.cast());
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = p;
}

/// Size and merge threshold `Int(C) + k/|C|` of a union-find root, side by side (one cache
/// line for both).
#[derive(Clone, Copy)]
struct RootInfo {
    size: u32,
    thresh: f32,
}

/// How far ahead (in edges) [`TiledMerger::add`] prefetches the union-find entries of an
/// edge's ends, and half as far ahead, those of their parents.
const PREFETCH: usize = 8;

/// [`Merger`] on [`Tiles`] nodes and tagged edges, with prefetching; the same merges in the
/// same order, so the same components and (numbered by pixel) the same labels.
struct TiledMerger<'t> {
    tiles: &'t Tiles,
    parent: Vec<u32>,
    root: Vec<RootInfo>,
    k: f32,
    /// Edges heavier than this never pass the merge test: every threshold is below `2k`
    /// (`k > 0`; by induction, `Int(C) + k/|C| <= 2k - k/|C|`, as a merge's weight is at most
    /// the threshold of the smaller side, of at most half the size), and below `k` for
    /// `k <= 0`. The margin covers rounding (relative `3e-7` per merge, at most ~32 merges
    /// deep along the smaller sides).
    cutoff: f32,
    min_size: usize,
    /// Tags of the rejected edges, as in [`Merger`].
    rejected: Vec<u32>,
    /// Union-find root -> label, for [`Self::finish`].
    map: Vec<u32>,
}

impl<'t> TiledMerger<'t> {
    /// A merger over `tiles.n` singletons, in buffers taken from `scratch` (handed back by
    /// [`Self::give_back`]).
    fn new(tiles: &'t Tiles, k: f32, min_size: usize, scratch: &mut GraphScratch) -> Self {
        let cutoff = if k > 0.0 { 2.0 * k * (1.0 + 1e-4) } else { k };
        let mut parent = std::mem::take(&mut scratch.parent);
        parent.clear();
        parent.extend(0..tiles.n as u32);
        let mut root = std::mem::take(&mut scratch.root);
        root.clear();
        root.resize(tiles.n, RootInfo { size: 1, thresh: k });
        let mut rejected = std::mem::take(&mut scratch.rejected);
        rejected.clear();
        Self {
            tiles,
            parent,
            root,
            k,
            cutoff,
            min_size,
            rejected,
            map: std::mem::take(&mut scratch.map),
        }
    }

    /// Path-halving find, as [`UnionFind::find`].
    #[inline]
    fn find(parent: &mut [u32], mut x: u32) -> u32 {
        while parent[x as usize] != x {
            let p = parent[x as usize];
            parent[x as usize] = parent[p as usize];
            x = parent[x as usize];
        }
        x
    }

    /// Joins roots `a` and `b` by size (ties: `a` wins), as [`UnionFind::union`].
    #[inline]
    fn union(parent: &mut [u32], root: &mut [RootInfo], a: u32, b: u32) -> u32 {
        let (sa, sb) = (root[a as usize].size, root[b as usize].size);
        let (big, small) = if sa >= sb { (a, b) } else { (b, a) };
        parent[small as usize] = big;
        root[big as usize].size = sa + sb;
        big
    }

    /// The merging pass over the next edges in weight order ([`Merger::add`]). Edges above
    /// the cutoff go straight to the rejected list: the ones whose ends are already joined
    /// are then extra entries there, which the minimum-size pass skips as it would have.
    fn add(&mut self, edges: &[u64]) {
        let (k, cutoff, keep) = (self.k, self.cutoff, self.min_size > 1);
        let tiles = self.tiles;
        let parent = &mut self.parent[..];
        let root = &mut self.root[..];
        for (i, &e) in edges.iter().enumerate() {
            if let Some(&f) = edges.get(i + 2 * PREFETCH) {
                let (fa, fb) = tiles.ends(f as u32);
                prefetch(parent.as_ptr().wrapping_add(fa as usize));
                prefetch(parent.as_ptr().wrapping_add(fb as usize));
            }
            if let Some(&f) = edges.get(i + PREFETCH) {
                let (fa, fb) = tiles.ends(f as u32);
                let (pa, pb) = (parent[fa as usize], parent[fb as usize]);
                prefetch(root.as_ptr().wrapping_add(pa as usize));
                prefetch(root.as_ptr().wrapping_add(pb as usize));
                prefetch(parent.as_ptr().wrapping_add(pa as usize));
                prefetch(parent.as_ptr().wrapping_add(pb as usize));
            }
            let w = key_weight(e.key());
            let tag = e as u32;
            if !(w <= cutoff) {
                if keep {
                    self.rejected.push(tag);
                }
                continue;
            }
            let (ea, eb) = tiles.ends(tag);
            let a = Self::find(parent, ea);
            let b = Self::find(parent, eb);
            if a == b {
                continue;
            }
            if w <= root[a as usize].thresh && w <= root[b as usize].thresh {
                let r = Self::union(parent, root, a, b) as usize;
                root[r].thresh = w + k / root[r].size as f32;
            } else if keep {
                self.rejected.push(tag);
            }
        }
    }

    /// The minimum-size pass and the labels, numbered by row-major pixel ([`Merger::finish`]).
    /// Called once, after the last [`Self::add`].
    fn finish(&mut self, width: usize, height: usize, active: &[bool]) -> (Vec<u32>, usize) {
        let (tiles, min_size) = (self.tiles, self.min_size);
        let parent = &mut self.parent[..];
        let root = &mut self.root[..];
        for &tag in &self.rejected {
            let (ea, eb) = tiles.ends(tag);
            let a = Self::find(parent, ea);
            let b = Self::find(parent, eb);
            if a != b
                && ((root[a as usize].size as usize) < min_size
                    || (root[b as usize].size as usize) < min_size)
            {
                Self::union(parent, root, a, b);
            }
        }
        // Every pixel's root in parallel (read-only walks: the parents no longer change),
        // then labels numbered by first appearance in row-major order, as before.
        let mut labels = vec![NO_SEGMENT; width * height];
        if width > 0 {
            let parent = &*parent;
            labels
                .par_chunks_mut(width)
                .enumerate()
                .for_each(|(y, row)| {
                    for (x, label) in row.iter_mut().enumerate() {
                        if active.get(y * width + x).copied().unwrap_or(false) {
                            let mut r = tiles.node(x, y);
                            while parent[r as usize] != r {
                                r = parent[r as usize];
                            }
                            *label = r;
                        }
                    }
                });
        }
        let map = &mut self.map;
        map.clear();
        map.resize(tiles.n, NO_SEGMENT);
        let mut count = 0u32;
        for label in labels.iter_mut().filter(|l| **l != NO_SEGMENT) {
            let m = &mut map[*label as usize];
            if *m == NO_SEGMENT {
                *m = count;
                count += 1;
            }
            *label = *m;
        }
        (labels, count as usize)
    }

    /// Hands the buffers back to `scratch` for the next call.
    fn give_back(self, scratch: &mut GraphScratch) {
        scratch.map = self.map;
        scratch.parent = self.parent;
        scratch.root = self.root;
        scratch.rejected = self.rejected;
    }
}

#[cfg(any(test, feature = "internals"))]
/// Edges of the 8-connected image graph between pixels with normals, weighted by
/// [`convexity_weight`], or [`JUMP_WEIGHT`] where the inverse depth of the two pixels differs
/// by more than `jump_ratio` of the larger (per pixel of distance).
///
/// Edges come out sorted by `(a, b)` (which [`sort_edges`] relies on for its ties).
pub fn image_edges(
    width: usize,
    height: usize,
    points: &[[f32; 3]],
    normals: &[[f32; 3]],
    inverse_depth: &[f32],
    jump_ratio: f32,
) -> Vec<Edge> {
    let bands = image_edge_bands(width, height, points, normals, inverse_depth, jump_ratio);
    let mut edges = Vec::with_capacity(bands.iter().map(|b| b.0.len()).sum());
    for (b, _) in bands {
        edges.extend(b);
    }
    edges
}

/// Rows per band of [`image_edge_bands`].
const BAND_ROWS: usize = 16;

/// The edges of [`image_edges`] in bands of [`BAND_ROWS`] rows (of the first vertex), in
/// parallel, each with the histogram of its top digits.
fn image_edge_bands(
    width: usize,
    height: usize,
    points: &[[f32; 3]],
    normals: &[[f32; 3]],
    inverse_depth: &[f32],
    jump_ratio: f32,
) -> Vec<(Vec<Edge>, Vec<u32>)> {
    let n = width * height;
    if n == 0 || points.len() < n || normals.len() < n || inverse_depth.len() < n {
        return Vec::new();
    }
    let valid = |i: usize| {
        let v = normals[i];
        v[0] != 0.0 || v[1] != 0.0 || v[2] != 0.0
    };
    (0..height.div_ceil(BAND_ROWS))
        .into_par_iter()
        .map(|band| {
            let rows = band * BAND_ROWS..((band + 1) * BAND_ROWS).min(height);
            let mut out = Vec::with_capacity(rows.len() * width * 4);
            let mut hist = vec![0u32; TOP_BUCKETS];
            for y in rows {
                for x in 0..width {
                    let i = y * width + x;
                    if !valid(i) {
                        continue;
                    }
                    let mut push = |j: usize, dist: f32| {
                        if !valid(j) {
                            return;
                        }
                        let (ri, rj) = (inverse_depth[i], inverse_depth[j]);
                        let w = if (ri - rj).abs() > jump_ratio * dist * ri.max(rj) {
                            JUMP_WEIGHT
                        } else {
                            convexity_weight(points[i], normals[i], points[j], normals[j])
                        };
                        let e = Edge {
                            w,
                            a: i as u32,
                            b: j as u32,
                        };
                        hist[top_digit(&e)] += 1;
                        out.push(e);
                    };
                    // In increasing order of the other vertex, so the edges come out sorted
                    // by (a, b), which [`sort_edges`] relies on for its ties.
                    if x + 1 < width {
                        push(i + 1, 1.0);
                    }
                    if y + 1 < height {
                        if x > 0 {
                            push(i + width - 1, std::f32::consts::SQRT_2);
                        }
                        push(i + width, 1.0);
                        if x + 1 < width {
                            push(i + width + 1, std::f32::consts::SQRT_2);
                        }
                    }
                }
            }
            (out, hist)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn convex_crease_weighs_less_than_concave() {
        // A roof ridge (convex) vs a valley (concave), seen from above (camera looks along +z,
        // normals face the camera, i.e. have negative z).
        let s = std::f32::consts::FRAC_1_SQRT_2;
        // Ridge: left face normal (-s, 0, -s), right face (s, 0, -s), ridge nearer the camera.
        let pl = [-0.1, 0.0, 1.1];
        let pr = [0.1, 0.0, 1.1];
        let convex = convexity_weight(pl, [-s, 0.0, -s], pr, [s, 0.0, -s]);
        // Valley: left face (s, 0, -s), right (-s, 0, -s), valley farther.
        let concave = convexity_weight(pl, [s, 0.0, -s], pr, [-s, 0.0, -s]);
        assert!((concave - 1.0).abs() < 1e-6, "{concave}");
        assert!((convex - 1.0).abs() < 1e-6 || convex < concave, "{convex}");
        // Smaller angles: squared is smaller.
        let c = 0.96f32.sqrt();
        let convex2 = convexity_weight(pl, [-0.2, 0.0, -c], pr, [0.2, 0.0, -c]);
        let concave2 = convexity_weight(pl, [0.2, 0.0, -c], pr, [-0.2, 0.0, -c]);
        assert!(convex2 < 0.5 * concave2, "{convex2} {concave2}");
    }

    /// xorshift64 in [0, 1).
    fn rng(seed: u64) -> impl FnMut() -> f64 {
        let mut s = seed;
        move || {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            (s >> 11) as f64 / (1u64 << 53) as f64
        }
    }

    /// The radix sort gives exactly the order of a stable comparison sort by
    /// `f32::total_cmp` (ties in input order), for weights with many ties, signed zeros,
    /// negatives, infinities and NaNs, at sizes around the small-sort cut-off and large ones.
    #[test]
    fn radix_sort_equals_stable_sort() {
        let mut r = rng(7);
        let special = [
            0.0,
            -0.0,
            2.0,
            -1.5,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::NAN,
            -f32::NAN,
            f32::MIN_POSITIVE,
            1e-30,
        ];
        for n in [0, 1, 2, 95, 96, 97, 500, 5_000, 100_000, 400_000] {
            for kind in 0..4 {
                let edges: Vec<Edge> = (0..n as u32)
                    .map(|i| {
                        let u = r();
                        let w = match kind {
                            // Few distinct values: long runs of ties.
                            0 => (u * 8.0).floor() as f32 * 0.25,
                            // Weights of real graphs: d or d^2 over many magnitudes.
                            1 => (u * 2.0).powi(1 + (i % 7) as i32) as f32,
                            // Anything, specials included.
                            2 => {
                                if u < 0.1 {
                                    special[(u * 100.0) as usize % special.len()]
                                } else {
                                    f32::from_bits((r() * u32::MAX as f64) as u32)
                                }
                            }
                            // One top digit for all (only the low bits differ).
                            _ => 1.0 + (u * 1e-3) as f32,
                        };
                        Edge { w, a: i, b: i + 1 }
                    })
                    .collect();
                let mut want = edges.clone();
                want.sort_by(|p, q| p.w.total_cmp(&q.w));
                let mut got = edges;
                sort_edges(&mut got);
                let same = got
                    .iter()
                    .zip(&want)
                    .all(|(g, w)| g.w.to_bits() == w.w.to_bits() && g.a == w.a && g.b == w.b);
                assert!(same && got.len() == want.len(), "n {n} kind {kind}");
            }
        }
    }

    /// The union-find implementation before the compact nodes and the rejected-edge list, kept
    /// as the reference.
    fn felzenszwalb_reference(
        n: usize,
        edges: &[Edge],
        k: f32,
        min_size: usize,
        active: &[bool],
    ) -> (Vec<u32>, usize) {
        let mut parent: Vec<u32> = (0..n as u32).collect();
        let mut size = vec![1u32; n];
        let mut thresh = vec![k; n];
        fn find(parent: &mut [u32], mut x: u32) -> u32 {
            while parent[x as usize] != x {
                let p = parent[x as usize];
                parent[x as usize] = parent[p as usize];
                x = parent[x as usize];
            }
            x
        }
        let union = |parent: &mut [u32], size: &mut [u32], a: u32, b: u32| {
            let (big, small) = if size[a as usize] >= size[b as usize] {
                (a, b)
            } else {
                (b, a)
            };
            parent[small as usize] = big;
            size[big as usize] += size[small as usize];
            big
        };
        for e in edges {
            let a = find(&mut parent, e.a);
            let b = find(&mut parent, e.b);
            if a != b && e.w <= thresh[a as usize] && e.w <= thresh[b as usize] {
                let r = union(&mut parent, &mut size, a, b);
                thresh[r as usize] = e.w + k / size[r as usize] as f32;
            }
        }
        if min_size > 1 {
            for e in edges {
                let a = find(&mut parent, e.a);
                let b = find(&mut parent, e.b);
                if a != b
                    && ((size[a as usize] as usize) < min_size
                        || (size[b as usize] as usize) < min_size)
                {
                    union(&mut parent, &mut size, a, b);
                }
            }
        }
        let mut map = vec![NO_SEGMENT; n];
        let mut labels = vec![NO_SEGMENT; n];
        let mut count = 0u32;
        for i in 0..n {
            if !active[i] {
                continue;
            }
            let r = find(&mut parent, i as u32) as usize;
            if map[r] == NO_SEGMENT {
                map[r] = count;
                count += 1;
            }
            labels[i] = map[r];
        }
        (labels, count as usize)
    }

    /// Same labels as the reference on 8-connected grids with piecewise-smooth random
    /// weights (regions, noise, ties), holes and several `k` / minimum sizes.
    #[test]
    fn felzenszwalb_equals_reference() {
        let mut r = rng(11);
        let (w, h) = (97, 61);
        for trial in 0..6 {
            let active: Vec<bool> = (0..w * h).map(|_| r() > 0.05).collect();
            let region = |i: usize| (i % w) / 17 + 7 * ((i / w) / 13);
            let mut edges = Vec::new();
            for y in 0..h {
                for x in 0..w {
                    let i = y * w + x;
                    let mut nb = vec![];
                    if x + 1 < w {
                        nb.push(i + 1);
                    }
                    if y + 1 < h {
                        if x > 0 {
                            nb.push(i + w - 1);
                        }
                        nb.push(i + w);
                        if x + 1 < w {
                            nb.push(i + w + 1);
                        }
                    }
                    for j in nb {
                        if !(active[i] && active[j]) {
                            continue;
                        }
                        let base = if region(i) == region(j) { 0.02 } else { 0.8 };
                        let wt = if trial % 2 == 0 {
                            (base * r()) as f32
                        } else {
                            // Quantised: many ties.
                            ((base * r() * 20.0).round() / 20.0) as f32
                        };
                        edges.push(Edge {
                            w: wt,
                            a: i as u32,
                            b: j as u32,
                        });
                    }
                }
            }
            sort_edges(&mut edges);
            for (k, min_size) in [(0.6, 200), (0.05, 1), (2.0, 30), (0.3, 0)] {
                let got = felzenszwalb(w * h, &edges, k, min_size, &active);
                let want = felzenszwalb_reference(w * h, &edges, k, min_size, &active);
                if min_size <= 1 && trial % 2 == 0 {
                    assert!(got.1 > 1, "trial {trial} k {k}: {} segments", got.1);
                }
                assert_eq!(got, want, "trial {trial} k {k} min {min_size}");
            }
        }
    }

    /// The fused image path (row buckets, tiled numbering, pipelined sort and merging) gives
    /// the labels of `felzenszwalb` on the sorted `image_edges`, on any number of threads, for
    /// sizes that are not whole tiles and for `k <= 0` (no cutoff), also with a side job run
    /// beside the union-find. The sizes shrink and grow from call to call, so the buffers kept
    /// between calls are reused at other sizes.
    #[test]
    fn image_graph_equals_separate_stages() {
        // One scratch for every size: what one call leaves must not change the next.
        let mut scratch = GraphScratch::new();
        for (w, h) in [(160, 120), (157, 119), (161, 122), (83, 64), (160, 120)] {
            image_graph_equals_separate_stages_at(w, h, &mut scratch);
        }
    }

    fn image_graph_equals_separate_stages_at(w: usize, h: usize, scratch: &mut GraphScratch) {
        let mut r = rng(3);
        let n = w * h;
        // Piecewise planes with noise, holes and depth steps; quantised normals give ties.
        let mut rho = vec![0.0f32; n];
        let mut normals = vec![[0.0f32; 3]; n];
        let mut points = vec![[0.0f32; 3]; n];
        for y in 0..h {
            for x in 0..w {
                let i = y * w + x;
                if r() < 0.03 {
                    continue;
                }
                let patch = (x / 40 + 4 * (y / 30)) as f64;
                rho[i] = (0.3 + 0.02 * patch + 0.001 * r()) as f32;
                let q = |v: f64| ((v * 16.0).round() / 16.0) as f32;
                let nx = q(0.3 * (patch * 0.7).sin() + 0.05 * r());
                let ny = q(0.3 * (patch * 1.3).cos() + 0.05 * r());
                let nz = -(1.0 - nx * nx - ny * ny).sqrt();
                normals[i] = [nx, ny, nz];
                let z = 1.0 / rho[i];
                points[i] = [
                    (x as f32 - 80.0) / 100.0 * z,
                    (y as f32 - 60.0) / 100.0 * z,
                    z,
                ];
            }
        }
        let active: Vec<bool> = normals.iter().map(|v| v[2] != 0.0).collect();
        let mut edges = image_edges(w, h, &points, &normals, &rho, 0.03);
        sort_edges(&mut edges);
        for (k, min_size) in [(0.6, 200), (0.05, 1), (0.3, 20), (0.0, 5), (-0.1, 1)] {
            let want = felzenszwalb(n, &edges, k, min_size, &active);
            assert!(want.1 > 3, "{} segments", want.1);
            for threads in [1, 2, 3] {
                let pool = rayon::ThreadPoolBuilder::new()
                    .num_threads(threads)
                    .build()
                    .unwrap();
                let got = pool.install(|| {
                    segment_image_graph(w, h, &points, &normals, &rho, 0.03, k, min_size, &active)
                });
                assert_eq!(got, want, "{w}x{h} k {k} min {min_size} threads {threads}");
                // The same labels with a side job, whose result comes back.
                let (got, side) = pool.install(|| {
                    let inputs = GraphInputs {
                        width: w,
                        height: h,
                        points: &points,
                        normals: &normals,
                        inverse_depth: &rho,
                        jump_ratio: 0.03,
                    };
                    segment_image_graph_beside(scratch, &inputs, k, min_size, &active, || {
                        rho.iter().filter(|&&r| r > 0.0).count()
                    })
                });
                assert_eq!(got, want, "beside: {w}x{h} k {k} threads {threads}");
                assert_eq!(side, active.iter().filter(|&&a| a).count());
            }
        }
    }

    #[test]
    fn fh_splits_two_cliques_joined_by_a_heavy_edge() {
        // Chain 0-1-2-3 (light), 3-4 heavy, chain 4-5-6-7 light.
        let mut edges = Vec::new();
        for i in 0..7u32 {
            let w = if i == 3 { 0.9 } else { 0.01 };
            edges.push(Edge { w, a: i, b: i + 1 });
        }
        sort_edges(&mut edges);
        let (labels, n) = felzenszwalb(8, &edges, 0.6, 1, &[true; 8]);
        assert_eq!(n, 2);
        assert_eq!(labels, vec![0, 0, 0, 0, 1, 1, 1, 1]);
        // With min size 5 they must merge.
        let (_, n) = felzenszwalb(8, &edges, 0.6, 5, &[true; 8]);
        assert_eq!(n, 1);
    }
}
