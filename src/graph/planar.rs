//! Projection of a nearly planar 3D pose graph to 2D and back (thesis 7.4.6, Algorithm 2).
//!
//! The plane is the least-squares fit of the positions (PCA). A pose's 2D heading is the
//! in-plane angle of the body axis that lies most in the plane over the trajectory; edges are
//! projected through the current estimate (`Z2 = P(X_a)^-1 P(X_a Z)`), with isotropic
//! translation information `tau` and the rotation information about the plane normal. After a
//! 2D optimisation, [`lift_to_3d`] rotates each pose about the normal by its heading change
//! and moves it in the plane, keeping its off-plane coordinate.

use glam::{DMat3, DQuat, DVec3};

use super::lie::Se2;
use super::pose_graph::{sesync_weights, PoseGraph2, PoseGraph3};
use super::GraphError;
use crate::geometry::Se3;

/// A fitted plane and the in-plane heading convention.
#[derive(Clone, Debug)]
pub struct PlaneProjection {
    /// A point of the plane (the centroid), metres.
    pub origin: DVec3,
    /// In-plane axes and the unit normal.
    pub axes: [DVec3; 3],
    /// RMS distance of the positions to the plane (metres).
    pub rms: f64,
    /// RMS in-plane spread of the positions (metres).
    pub extent: f64,
    /// Body axis (0 = x, 1 = y, 2 = z) whose in-plane direction defines the heading.
    pub heading_axis: usize,
}

fn project_pose(p: &Se3, pp: &PlaneProjection) -> Se2 {
    let d = p.translation - pp.origin;
    let a = p.rotation_matrix().col(pp.heading_axis);
    Se2::new(
        d.dot(pp.axes[0]),
        d.dot(pp.axes[1]),
        a.dot(pp.axes[1]).atan2(a.dot(pp.axes[0])),
    )
}

/// Fits the plane; errors unless `rms <= max_ratio * extent` (a nearly planar trajectory).
pub fn fit_plane(g: &PoseGraph3, max_ratio: f64) -> Result<PlaneProjection, GraphError> {
    let pts = g.positions();
    if pts.len() < 3 {
        return Err(GraphError::Invalid("too few poses to fit a plane".into()));
    }
    let n = pts.len() as f64;
    let c = pts.iter().copied().sum::<DVec3>() / n;
    let mut m = nalgebra::Matrix3::<f64>::zeros();
    for p in &pts {
        let d = *p - c;
        let v = nalgebra::Vector3::new(d.x, d.y, d.z);
        m += v * v.transpose();
    }
    let eig = m.symmetric_eigen();
    let mut order = [0usize, 1, 2];
    order.sort_by(|&a, &b| eig.eigenvalues[b].total_cmp(&eig.eigenvalues[a]));
    let col = |k: usize| {
        let v = eig.eigenvectors.column(order[k]);
        DVec3::new(v[0], v[1], v[2])
    };
    let (e1, e2) = (col(0), col(1));
    let normal = e1.cross(e2).normalize();
    let rms = (eig.eigenvalues[order[2]].max(0.0) / n).sqrt();
    let extent = ((eig.eigenvalues[order[0]] + eig.eigenvalues[order[1]]).max(0.0) / n).sqrt();
    if !(rms <= max_ratio * extent) {
        return Err(GraphError::Invalid(format!(
            "trajectory is not planar: {rms:.3} m off-plane RMS for {extent:.3} m extent"
        )));
    }
    let heading_axis = (0..3)
        .max_by(|&a, &b| {
            let s = |k: usize| {
                g.poses
                    .iter()
                    .map(|p| 1.0 - p.rotation_matrix().col(k).dot(normal).powi(2))
                    .sum::<f64>()
            };
            s(a).total_cmp(&s(b))
        })
        .unwrap_or(0);
    Ok(PlaneProjection {
        origin: c,
        axes: [e1, e2, normal],
        rms,
        extent,
        heading_axis,
    })
}

/// Projects a nearly planar SE(3) graph to SE(2) (same ids, fixed flags and edge order).
pub fn project_to_2d(
    g: &PoseGraph3,
    max_ratio: f64,
) -> Result<(PoseGraph2, PlaneProjection), GraphError> {
    let pp = fit_plane(g, max_ratio)?;
    let mut g2 = PoseGraph2::new();
    for (id, p) in g.ids.iter().zip(&g.poses) {
        g2.add_vertex(*id, project_pose(p, &pp))?;
    }
    g2.fixed.clone_from(&g.fixed);
    for e in &g.edges {
        let xa = g.poses[e.from];
        let z2 = project_pose(&xa, &pp).inverse() * project_pose(&(xa * e.measurement), &pp);
        let (_, tau) = sesync_weights(&e.information, 3, 6);
        let nb = xa.rotation.conjugate() * pp.axes[2];
        let mut kz = 0.0;
        for r in 0..3 {
            for c in 0..3 {
                kz += nb[r] * e.information[(r + 3) * 6 + c + 3] * nb[c];
            }
        }
        let info = vec![tau, 0.0, 0.0, 0.0, tau, 0.0, 0.0, 0.0, kz.max(1e-12)];
        g2.add_edge_by_index(e.from, e.to, z2, info)?;
    }
    Ok((g2, pp))
}

/// Maps optimised 2D poses back to 3D: each original pose is rotated about the plane normal by
/// its heading change and moved in the plane; its off-plane coordinate is kept.
pub fn lift_to_3d(original: &PoseGraph3, optimised: &PoseGraph2, pp: &PlaneProjection) -> Vec<Se3> {
    original
        .poses
        .iter()
        .zip(&optimised.poses)
        .map(|(p3, p2)| {
            let before = project_pose(p3, pp);
            let dtheta = p2.theta - before.theta;
            let r = DMat3::from_axis_angle(pp.axes[2], dtheta) * p3.rotation_matrix();
            let off = (p3.translation - pp.origin).dot(pp.axes[2]);
            let t = pp.origin + pp.axes[0] * p2.x + pp.axes[1] * p2.y + pp.axes[2] * off;
            Se3::new(DQuat::from_mat3(&r), t)
        })
        .collect()
}
