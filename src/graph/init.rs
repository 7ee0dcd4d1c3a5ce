//! Initial estimates that avoid the local minima an optimiser falls into from odometry:
//! the spanning-tree (odometry) estimate, the linear approximation for 2D graphs (orientation
//! estimation with 2-pi regularisation, then linear translations: Carlone et al. 2011, the
//! thesis' "Linear 2D") and chordal rotation initialisation for 3D (Martinec & Pajdla 2007;
//! Carlone et al. 2015: relaxed rotations by sparse linear least squares, projected to SO(3),
//! then linear translations).

use std::collections::VecDeque;

use faer::prelude::*;
use faer::sparse::{SparseColMat, Triplet};
use faer::Side;
use glam::{DMat3, DQuat, DVec3};

use super::lie::{project_to_so3, Se2};
use super::pose_graph::{sesync_weights, PoseGraph, PoseGraph2, PoseGraph3};
use super::GraphError;
use crate::geometry::Se3;

/// How to initialise a pose graph before the non-linear optimisation.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum InitMethod {
    /// Linear 2D for SE(2) graphs, chordal for SE(3) graphs.
    #[default]
    Auto,
    /// Keep the given poses (the file's, or the spanning tree of odometry when it had none).
    Odometry,
    /// Linear approximation (2D only).
    Linear,
    /// Chordal relaxation of the rotations (3D; in 2D it falls back to Linear).
    Chordal,
}

/// Solves the SPD system `A X = B` (A from upper-or-full triplets, duplicates summed;
/// `B` column-major `n x k`).
pub(crate) fn solve_spd(
    n: usize,
    triplets: &[Triplet<usize, usize, f64>],
    b: &[f64],
    k: usize,
) -> Result<Vec<f64>, GraphError> {
    let a = SparseColMat::<usize, f64>::try_new_from_triplets(n, n, triplets)
        .map_err(|e| GraphError::Linear(format!("{e:?}")))?;
    let llt = a
        .sp_cholesky(Side::Upper)
        .map_err(|_| GraphError::SingularSystem)?;
    let mut x = Mat::<f64>::from_fn(n, k, |r, c| b[c * n + r]);
    llt.solve_in_place(x.as_mut());
    let mut out = vec![0.0; n * k];
    for c in 0..k {
        for r in 0..n {
            out[c * n + r] = x[(r, c)];
        }
    }
    if out.iter().any(|v| !v.is_finite()) {
        return Err(GraphError::NonFinite("linear initialisation".into()));
    }
    Ok(out)
}

/// Translations by linear least squares given rotations: minimises
/// `sum tau ||tj - ti - Ri tij||^2` with the root's translation fixed. `rot[i]` are the
/// rotations, `meas[k] = (i, j, tij, tau)`; returns the translations.
fn linear_translations(
    n: usize,
    root: usize,
    root_t: DVec3,
    rot: &[DMat3],
    meas: &[(usize, usize, DVec3, f64)],
) -> Result<Vec<DVec3>, GraphError> {
    let idx: Vec<usize> = (0..n)
        .map(|i| {
            if i < root {
                i
            } else if i == root {
                usize::MAX
            } else {
                i - 1
            }
        })
        .collect();
    let m = n - 1;
    if m == 0 {
        return Ok(vec![root_t]);
    }
    let mut trip = Vec::with_capacity(meas.len() * 3 + m);
    let mut b = vec![0.0; m * 3];
    for &(i, j, tij, tau) in meas {
        let c = rot[i] * tij; // tj - ti = c
        let (a, bb) = (idx[i], idx[j]);
        if a != usize::MAX {
            trip.push(Triplet::new(a, a, tau));
            for d in 0..3 {
                b[d * m + a] -= tau * c[d];
            }
        }
        if bb != usize::MAX {
            trip.push(Triplet::new(bb, bb, tau));
            for d in 0..3 {
                b[d * m + bb] += tau * c[d];
            }
        }
        match (a != usize::MAX, bb != usize::MAX) {
            (true, true) => {
                let (lo, hi) = (a.min(bb), a.max(bb));
                trip.push(Triplet::new(lo, hi, -tau));
            }
            (true, false) => {
                // tj = root_t known: tau (ti - (root_t - c))
                for d in 0..3 {
                    b[d * m + a] += tau * root_t[d];
                }
            }
            (false, true) => {
                for d in 0..3 {
                    b[d * m + bb] += tau * root_t[d];
                }
            }
            _ => {}
        }
    }
    let x = solve_spd(m, &trip, &b, 3)?;
    Ok((0..n)
        .map(|i| {
            if i == root {
                root_t
            } else {
                DVec3::new(x[idx[i]], x[m + idx[i]], x[2 * m + idx[i]])
            }
        })
        .collect())
}

/// Linear 2D initialisation (orientations with 2-pi regularisation along a spanning tree,
/// then translations), in place. The gauge vertex keeps its pose.
pub fn initialize_linear_2d(g: &mut PoseGraph2) -> Result<(), GraphError> {
    let root = g.check_connected()?;
    let n = g.poses.len();
    // Unwrapped orientations along a BFS spanning tree.
    let adj = g.adjacency();
    let mut tree = vec![f64::NAN; n];
    tree[root] = g.poses[root].theta;
    let mut q = VecDeque::from([root]);
    while let Some(i) = q.pop_front() {
        for &(j, k, fwd) in &adj[i] {
            if tree[j].is_nan() {
                let z = g.edges[k].measurement.theta;
                tree[j] = if fwd { tree[i] + z } else { tree[i] - z };
                q.push_back(j);
            }
        }
    }
    let idx: Vec<usize> = (0..n)
        .map(|i| {
            if i < root {
                i
            } else if i == root {
                usize::MAX
            } else {
                i - 1
            }
        })
        .collect();
    let m = n - 1;
    let theta = if m == 0 {
        tree.clone()
    } else {
        let mut trip = Vec::new();
        let mut b = vec![0.0; m];
        for e in &g.edges {
            let (i, j) = (e.from, e.to);
            let w = e.information[8];
            let two_pi = std::f64::consts::TAU;
            let kk = ((tree[j] - tree[i] - e.measurement.theta) / two_pi).round();
            let d = e.measurement.theta + two_pi * kk; // theta_j - theta_i = d
            let (a, bb) = (idx[i], idx[j]);
            if a != usize::MAX {
                trip.push(Triplet::new(a, a, w));
                b[a] -= w * d;
            } else {
                b[bb] += w * tree[root];
            }
            if bb != usize::MAX {
                trip.push(Triplet::new(bb, bb, w));
                b[bb] += w * d;
            } else {
                b[a] += w * tree[root];
            }
            if a != usize::MAX && bb != usize::MAX {
                trip.push(Triplet::new(a.min(bb), a.max(bb), -w));
            }
        }
        let x = solve_spd(m, &trip, &b, 1)?;
        (0..n)
            .map(|i| if i == root { tree[root] } else { x[idx[i]] })
            .collect()
    };
    let rot: Vec<DMat3> = theta.iter().map(|&t| DMat3::from_rotation_z(t)).collect();
    let meas: Vec<_> = g
        .edges
        .iter()
        .map(|e| {
            (
                e.from,
                e.to,
                DVec3::new(e.measurement.x, e.measurement.y, 0.0),
                sesync_weights(&e.information, 2, 3).1,
            )
        })
        .collect();
    let root_t = DVec3::new(g.poses[root].x, g.poses[root].y, 0.0);
    let t = linear_translations(n, root, root_t, &rot, &meas)?;
    for i in 0..n {
        g.poses[i] = Se2::new(t[i].x, t[i].y, theta[i]);
    }
    Ok(())
}

/// Chordal initialisation of an SE(3) graph in place: rotations from the relaxed linear
/// problem `min sum kappa ||Rj - Ri Rij||_F^2` projected to SO(3), then linear translations.
pub fn initialize_chordal_3d(g: &mut PoseGraph3) -> Result<(), GraphError> {
    let root = g.check_connected()?;
    let n = g.poses.len();
    let idx: Vec<usize> = (0..n)
        .map(|i| {
            if i < root {
                i
            } else if i == root {
                usize::MAX
            } else {
                i - 1
            }
        })
        .collect();
    let m = n - 1;
    let r_root = g.poses[root].rotation_matrix();
    let mut rot = vec![r_root; n];
    if m > 0 {
        // Unknowns x_i^k = (row k of R_i)^T, three right-hand sides; x_j = Rij^T x_i.
        let mut trip = Vec::with_capacity(g.edges.len() * 15);
        let mut b = vec![0.0; 3 * m * 3];
        let nn = 3 * m;
        for e in &g.edges {
            let (kappa, _) = sesync_weights(&e.information, 3, 6);
            let rij = e.measurement.rotation_matrix();
            let (a, bb) = (idx[e.from], idx[e.to]);
            for (v, _) in [(a, 0), (bb, 1)] {
                if v != usize::MAX {
                    for d in 0..3 {
                        trip.push(Triplet::new(3 * v + d, 3 * v + d, kappa));
                    }
                }
            }
            match (a != usize::MAX, bb != usize::MAX) {
                (true, true) => {
                    // H_ab = -kappa Rij (block (a,b)), upper triangle only.
                    for r in 0..3 {
                        for c in 0..3 {
                            if a < bb {
                                trip.push(Triplet::new(
                                    3 * a + r,
                                    3 * bb + c,
                                    -kappa * rij.col(c)[r],
                                ));
                            } else {
                                // block (b,a) = -kappa Rij^T
                                trip.push(Triplet::new(
                                    3 * bb + r,
                                    3 * a + c,
                                    -kappa * rij.col(r)[c],
                                ));
                            }
                        }
                    }
                }
                (true, false) => {
                    // x_j known (root): b_a += kappa Rij x_j
                    for k in 0..3 {
                        let xj = r_root.row(k);
                        let v = rij * xj;
                        for d in 0..3 {
                            b[k * nn + 3 * a + d] += kappa * v[d];
                        }
                    }
                }
                (false, true) => {
                    for k in 0..3 {
                        let xi = r_root.row(k);
                        let v = rij.transpose() * xi;
                        for d in 0..3 {
                            b[k * nn + 3 * bb + d] += kappa * v[d];
                        }
                    }
                }
                _ => {}
            }
        }
        let x = solve_spd(nn, &trip, &b, 3)?;
        for i in 0..n {
            if i == root {
                continue;
            }
            let v = idx[i];
            let row = |k: usize| {
                DVec3::new(
                    x[k * nn + 3 * v],
                    x[k * nn + 3 * v + 1],
                    x[k * nn + 3 * v + 2],
                )
            };
            // Rows -> matrix: transpose of the matrix whose columns are the rows.
            let m3 = DMat3::from_cols(row(0), row(1), row(2)).transpose();
            rot[i] = project_to_so3(m3);
        }
    }
    let meas: Vec<_> = g
        .edges
        .iter()
        .map(|e| {
            (
                e.from,
                e.to,
                e.measurement.translation,
                sesync_weights(&e.information, 3, 6).1,
            )
        })
        .collect();
    let t = linear_translations(n, root, g.poses[root].translation, &rot, &meas)?;
    for i in 0..n {
        g.poses[i] = Se3::new(DQuat::from_mat3(&rot[i]), t[i]);
    }
    Ok(())
}

/// Applies `method` to an SE(2) graph.
pub fn initialize_2d(g: &mut PoseGraph2, method: InitMethod) -> Result<(), GraphError> {
    match method {
        InitMethod::Odometry => Ok(()),
        InitMethod::Auto | InitMethod::Linear | InitMethod::Chordal => initialize_linear_2d(g),
    }
}

/// Applies `method` to an SE(3) graph.
pub fn initialize_3d(g: &mut PoseGraph3, method: InitMethod) -> Result<(), GraphError> {
    match method {
        InitMethod::Odometry => Ok(()),
        InitMethod::Linear => Err(GraphError::Invalid(
            "the linear initialisation is for 2D graphs; use chordal".into(),
        )),
        InitMethod::Auto | InitMethod::Chordal => initialize_chordal_3d(g),
    }
}

/// Keeps `PoseGraph` in scope for docs.
#[allow(dead_code)]
fn _doc<P: super::pose_graph::Pose>(_: &PoseGraph<P>) {}
