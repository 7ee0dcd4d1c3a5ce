//! Graph segmentation: convex/concave edge weights (thesis eq. 5.1 / 6.26) and
//! Felzenszwalb-Huttenlocher merging with sorted edges and union-find.

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
        // Path halving.
        while self.parent[x as usize] != x {
            let p = self.parent[x as usize];
            self.parent[x as usize] = self.parent[p as usize];
            x = self.parent[x as usize];
        }
        x
    }
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

/// Sorts edges by weight with a stable radix sort (`radsort`): ties keep their input order.
/// [`image_edges`] and [`crate::segment::TriMesh::weighted_edges`] emit edges sorted by
/// `(a, b)`, so the result is the order by `(w, a, b)` and segmentation is deterministic
/// (about 5x faster than a comparison sort of the 1.2 M edges of a 640x480 image).
pub fn sort_edges(edges: &mut [Edge]) {
    radsort::sort_by_key(edges, |e| e.w);
}

/// Felzenszwalb-Huttenlocher segmentation of a graph with `n` vertices.
///
/// `edges` must be sorted with [`sort_edges`]. Components `C1`, `C2` joined by an edge of
/// weight `w` merge when `w <= min(Int(C1) + k/|C1|, Int(C2) + k/|C2|)`, `Int` being the
/// largest weight of the component's minimum spanning tree. Afterwards, components smaller
/// than `min_size` vertices merge along the remaining edges in weight order. `active[i]` false
/// marks vertices that belong to no segment (they get [`NO_SEGMENT`]).
///
/// Returns one label per vertex, numbered `0..count` in order of first appearance, and `count`.
pub fn felzenszwalb(
    n: usize,
    edges: &[Edge],
    k: f32,
    min_size: usize,
    active: &[bool],
) -> (Vec<u32>, usize) {
    let mut uf = UnionFind::new(n, k);
    for e in edges {
        let a = uf.find(e.a);
        let b = uf.find(e.b);
        if a != b && e.w <= uf.thresh[a as usize] && e.w <= uf.thresh[b as usize] {
            let r = uf.union(a, b);
            uf.thresh[r as usize] = e.w + k / uf.size[r as usize] as f32;
        }
    }
    if min_size > 1 {
        for e in edges {
            let a = uf.find(e.a);
            let b = uf.find(e.b);
            if a != b
                && ((uf.size[a as usize] as usize) < min_size
                    || (uf.size[b as usize] as usize) < min_size)
            {
                uf.union(a, b);
            }
        }
    }
    let mut map = vec![NO_SEGMENT; n];
    let mut labels = vec![NO_SEGMENT; n];
    let mut count = 0u32;
    for i in 0..n {
        if !active.get(i).copied().unwrap_or(false) {
            continue;
        }
        let r = uf.find(i as u32) as usize;
        if map[r] == NO_SEGMENT {
            map[r] = count;
            count += 1;
        }
        labels[i] = map[r];
    }
    (labels, count as usize)
}

/// Edges of the 8-connected image graph between pixels with normals, weighted by
/// [`convexity_weight`], or [`JUMP_WEIGHT`] where the inverse depth of the two pixels differs
/// by more than `jump_ratio` of the larger (per pixel of distance).
pub fn image_edges(
    width: usize,
    height: usize,
    points: &[[f32; 3]],
    normals: &[[f32; 3]],
    inverse_depth: &[f32],
    jump_ratio: f32,
) -> Vec<Edge> {
    let valid = |i: usize| {
        let n = normals[i];
        n[0] != 0.0 || n[1] != 0.0 || n[2] != 0.0
    };
    let rows: Vec<Vec<Edge>> = (0..height)
        .into_par_iter()
        .map(|y| {
            let mut out = Vec::with_capacity(width * 4);
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
                    out.push(Edge {
                        w,
                        a: i as u32,
                        b: j as u32,
                    });
                };
                // In increasing order of the other vertex, so the edges come out sorted by
                // (a, b), which [`sort_edges`] relies on for its ties.
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
            out
        })
        .collect();
    let mut edges = Vec::with_capacity(rows.iter().map(Vec::len).sum());
    for r in rows {
        edges.extend(r);
    }
    edges
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
