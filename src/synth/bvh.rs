//! Bounding-volume hierarchy over the scene's primitives (surface-area heuristic, sweep
//! build), flattened to the [`PackedNode`] layout both ray casters traverse.

use super::raycast::{PackedNode, PackedPrim, MAX_STACK};

/// An axis-aligned box in world coordinates (metres).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Aabb {
    /// Minimum corner.
    pub min: [f64; 3],
    /// Maximum corner.
    pub max: [f64; 3],
}

impl Aabb {
    /// The empty box (union identity).
    pub const EMPTY: Aabb = Aabb {
        min: [f64::INFINITY; 3],
        max: [f64::NEG_INFINITY; 3],
    };

    /// Smallest box holding both.
    pub fn union(&self, o: &Aabb) -> Aabb {
        let mut r = *self;
        for k in 0..3 {
            r.min[k] = r.min[k].min(o.min[k]);
            r.max[k] = r.max[k].max(o.max[k]);
        }
        r
    }

    /// Surface area (0 for the empty box).
    pub fn area(&self) -> f64 {
        let e = [
            self.max[0] - self.min[0],
            self.max[1] - self.min[1],
            self.max[2] - self.min[2],
        ];
        if e.iter().any(|x| *x < 0.0) {
            return 0.0;
        }
        2.0 * (e[0] * e[1] + e[1] * e[2] + e[0] * e[2])
    }

    /// Centre point.
    pub fn center(&self) -> [f64; 3] {
        [
            0.5 * (self.min[0] + self.max[0]),
            0.5 * (self.min[1] + self.max[1]),
            0.5 * (self.min[2] + self.max[2]),
        ]
    }
}

const LEAF_SIZE: usize = 2;

/// Builds the BVH: returns the nodes and the primitives reordered into leaf order.
pub fn build(prims: &[(PackedPrim, Aabb)]) -> (Vec<PackedNode>, Vec<PackedPrim>) {
    let mut order: Vec<usize> = (0..prims.len()).collect();
    let mut nodes: Vec<PackedNode> = Vec::new();
    if prims.is_empty() {
        return (nodes, Vec::new());
    }
    nodes.push(PackedNode {
        min: [0.0; 4],
        max: [0.0; 4],
    });
    // Work list: (node index, start, end, depth).
    let mut work = vec![(0usize, 0usize, prims.len(), 0usize)];
    while let Some((ni, start, end, depth)) = work.pop() {
        let bounds = order[start..end]
            .iter()
            .fold(Aabb::EMPTY, |b, &i| b.union(&prims[i].1));
        let count = end - start;
        let split = if count <= LEAF_SIZE {
            None
        } else {
            best_split(prims, &mut order[start..end], depth)
        };
        let (a, c) = match split {
            None => (start as u32, count as u32),
            Some(mid) => {
                let left = nodes.len();
                nodes.push(PackedNode {
                    min: [0.0; 4],
                    max: [0.0; 4],
                });
                nodes.push(PackedNode {
                    min: [0.0; 4],
                    max: [0.0; 4],
                });
                work.push((left, start, start + mid, depth + 1));
                work.push((left + 1, start + mid, end, depth + 1));
                (left as u32, 0)
            }
        };
        nodes[ni] = PackedNode {
            min: [
                bounds.min[0] as f32,
                bounds.min[1] as f32,
                bounds.min[2] as f32,
                f32::from_bits(a),
            ],
            max: [
                bounds.max[0] as f32,
                bounds.max[1] as f32,
                bounds.max[2] as f32,
                f32::from_bits(c),
            ],
        };
    }
    // Slightly inflate f32 boxes so rounding never culls a surface lying on a face.
    for n in &mut nodes {
        for k in 0..3 {
            n.min[k] -= 1e-4 + n.min[k].abs() * 1e-6;
            n.max[k] += 1e-4 + n.max[k].abs() * 1e-6;
        }
    }
    let reordered = order.iter().map(|&i| prims[i].0).collect();
    (nodes, reordered)
}

/// Sorts `idx` along the best axis and returns the split position (SAH over a sweep), or
/// `None` to make a leaf. Deep nodes fall back to a median split so the depth stays below
/// the traversal stack.
fn best_split(prims: &[(PackedPrim, Aabb)], idx: &mut [usize], depth: usize) -> Option<usize> {
    let n = idx.len();
    if depth + 2 >= MAX_STACK {
        return None;
    }
    let mut best: Option<(f64, usize, usize)> = None; // (cost, axis, split)
    for axis in 0..3 {
        idx.sort_by(|&a, &b| prims[a].1.center()[axis].total_cmp(&prims[b].1.center()[axis]));
        let mut right_area = vec![0.0; n];
        let mut acc = Aabb::EMPTY;
        for i in (0..n).rev() {
            acc = acc.union(&prims[idx[i]].1);
            right_area[i] = acc.area();
        }
        let mut acc = Aabb::EMPTY;
        for i in 0..n - 1 {
            acc = acc.union(&prims[idx[i]].1);
            let cost = acc.area() * (i + 1) as f64 + right_area[i + 1] * (n - i - 1) as f64;
            if best.is_none_or(|b| cost < b.0) {
                best = Some((cost, axis, i + 1));
            }
        }
    }
    let (cost, axis, split) = best?;
    let total = idx
        .iter()
        .fold(Aabb::EMPTY, |b, &i| b.union(&prims[i].1))
        .area();
    // Leaf if splitting does not pay (traversal cost ~1 box test, intersection ~1.5).
    if n <= 4 && cost * 1.5 >= total * 1.5 * n as f64 - total {
        return None;
    }
    if depth > 24 {
        idx.sort_by(|&a, &b| prims[a].1.center()[axis].total_cmp(&prims[b].1.center()[axis]));
        return Some(n / 2);
    }
    idx.sort_by(|&a, &b| prims[a].1.center()[axis].total_cmp(&prims[b].1.center()[axis]));
    Some(split)
}
