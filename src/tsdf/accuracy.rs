//! Accuracy and completeness of a mesh against a known surface.

use std::collections::HashMap;
use std::hash::BuildHasherDefault;

use glam::DVec3;
use rayon::prelude::*;
use rustc_hash::FxHasher;

/// How close a mesh is to the true surface.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize)]
pub struct MeshAccuracy {
    /// Mesh vertices measured.
    pub vertices: usize,
    /// Mean distance of the vertices to the true surface, metres.
    pub mean_m: f64,
    /// 90th percentile of that distance, metres.
    pub p90_m: f64,
    /// Share of the reference surface points with a mesh vertex within `radius_m`.
    pub completeness: f64,
    /// Reference surface points (true surface seen by some frame, thinned).
    pub reference_points: usize,
    /// The completeness radius, metres.
    pub radius_m: f64,
}

type Grid = HashMap<[i64; 3], Vec<DVec3>, BuildHasherDefault<FxHasher>>;

fn cell(p: DVec3, size: f64) -> [i64; 3] {
    [
        (p.x / size).floor() as i64,
        (p.y / size).floor() as i64,
        (p.z / size).floor() as i64,
    ]
}

/// One point per `cell_m` cube (the first), so that a surface seen by many frames counts by
/// area rather than by how often it was seen.
pub fn thin_points(points: &[DVec3], cell_m: f64) -> Vec<DVec3> {
    let mut seen: HashMap<[i64; 3], (), BuildHasherDefault<FxHasher>> = HashMap::default();
    points
        .iter()
        .copied()
        .filter(|&p| p.is_finite() && seen.insert(cell(p, cell_m), ()).is_none())
        .collect()
}

/// Distances of `vertices` (world, metres) to the true surface given by `distance` (metres
/// from a world point), and the share of `reference` points (on the true surface, thinned)
/// with a vertex within `radius_m`.
pub fn mesh_accuracy(
    vertices: &[[f32; 3]],
    distance: impl Fn(DVec3) -> f64 + Sync,
    reference: &[DVec3],
    radius_m: f64,
) -> MeshAccuracy {
    let pts: Vec<DVec3> = vertices
        .iter()
        .map(|v| DVec3::new(f64::from(v[0]), f64::from(v[1]), f64::from(v[2])))
        .collect();
    let mut d: Vec<f64> = pts.par_iter().map(|&p| distance(p)).collect();
    d.sort_by(f64::total_cmp);
    let mean = if d.is_empty() {
        f64::NAN
    } else {
        d.iter().sum::<f64>() / d.len() as f64
    };
    let p90 = if d.is_empty() {
        f64::NAN
    } else {
        d[((d.len() - 1) as f64 * 0.9).round() as usize]
    };
    let mut grid = Grid::default();
    for &p in &pts {
        grid.entry(cell(p, radius_m)).or_default().push(p);
    }
    let r2 = radius_m * radius_m;
    let covered = reference
        .par_iter()
        .filter(|&&q| {
            let c = cell(q, radius_m);
            for dx in -1..=1 {
                for dy in -1..=1 {
                    for dz in -1..=1 {
                        if let Some(v) = grid.get(&[c[0] + dx, c[1] + dy, c[2] + dz]) {
                            if v.iter().any(|p| p.distance_squared(q) <= r2) {
                                return true;
                            }
                        }
                    }
                }
            }
            false
        })
        .count();
    MeshAccuracy {
        vertices: pts.len(),
        mean_m: mean,
        p90_m: p90,
        completeness: if reference.is_empty() {
            f64::NAN
        } else {
            covered as f64 / reference.len() as f64
        },
        reference_points: reference.len(),
        radius_m,
    }
}
