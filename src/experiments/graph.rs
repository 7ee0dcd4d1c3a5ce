//! The pose-graph suite of the thesis' chapter 7 (tables 7.1-7.4 analogues): the data sets it
//! runs on, and the tilted-plane experiment of 7.4.6 (a 2D graph laid on a plane in 3D with
//! small out-of-plane noise, so that the planar projection has a ground truth).

use crate::geometry::Se3;
use crate::graph::{GraphError, PoseGraph2, PoseGraph3};
use crate::scale::particle::standard_normal;

/// The data sets of the thesis suite: file under `../shared/data/posegraph`, and its ground
/// truth file where one exists.
pub const THESIS_DATA: &[(&str, Option<&str>)] = &[
    (
        "carlone/M3500.g2o",
        Some("isam/groundtruth/manhattanOlson3500_groundtruth.txt"),
    ),
    (
        "carlone/M3500a.g2o",
        Some("isam/groundtruth/manhattanOlson3500_groundtruth.txt"),
    ),
    (
        "carlone/M3500b.g2o",
        Some("isam/groundtruth/manhattanOlson3500_groundtruth.txt"),
    ),
    (
        "carlone/M3500c.g2o",
        Some("isam/groundtruth/manhattanOlson3500_groundtruth.txt"),
    ),
    (
        "isam/manhattanOlson3500.txt",
        Some("isam/groundtruth/manhattanOlson3500_groundtruth.txt"),
    ),
    (
        "isam/city10000.txt",
        Some("isam/groundtruth/city10000_groundtruth.txt"),
    ),
    ("carlone/INTEL.g2o", None),
    ("carlone/MIT.g2o", None),
    (
        "isam/sphere2500.txt",
        Some("isam/groundtruth/sphere2500_groundtruth.txt"),
    ),
    ("isam/torus10000.txt", None),
    ("se-sync/parking-garage.g2o", None),
    ("se-sync/kitti_00.g2o", None),
    ("se-sync/kitti_05.g2o", None),
];

/// The plane of the tilted-plane experiment: rotation by 20 degrees about (1, 1, 0), then a
/// shift of (1, 2, 3) m.
pub fn tilt() -> (glam::DMat3, glam::DVec3) {
    (
        glam::DMat3::from_axis_angle(
            glam::DVec3::new(1.0, 1.0, 0.0).normalize(),
            20f64.to_radians(),
        ),
        glam::DVec3::new(1.0, 2.0, 3.0),
    )
}

/// A 2D graph laid on the tilted plane of [`tilt`]: vertices lifted exactly, measurements
/// given 1 cm of z noise and 0.3 degrees of roll/pitch noise (seeded), with the matching
/// information; the 2D information is kept for x, y and yaw.
pub fn lift_to_tilted_plane(g2: &PoseGraph2) -> Result<PoseGraph3, GraphError> {
    use rand::SeedableRng;
    let (r0, t0) = tilt();
    let q0 = glam::DQuat::from_mat3(&r0);
    let mut rng = rand_pcg::Pcg64::seed_from_u64(35);
    let (sz, sr) = (0.01, 0.3f64.to_radians());
    let mut g3 = PoseGraph3::new();
    for (id, p) in g2.ids.iter().zip(&g2.poses) {
        let q = q0 * glam::DQuat::from_rotation_z(p.theta);
        g3.add_vertex(*id, Se3::new(q, r0 * glam::DVec3::new(p.x, p.y, 0.0) + t0))?;
    }
    for e in &g2.edges {
        let z = e.measurement;
        let q = glam::DQuat::from_rotation_z(z.theta)
            * glam::DQuat::from_euler(
                glam::EulerRot::XYZ,
                sr * standard_normal(&mut rng),
                sr * standard_normal(&mut rng),
                0.0,
            );
        let m = Se3::new(
            q,
            glam::DVec3::new(z.x, z.y, sz * standard_normal(&mut rng)),
        );
        let i2 = &e.information;
        let mut info = vec![0.0; 36];
        for r in 0..2 {
            for c in 0..2 {
                info[r * 6 + c] = i2[r * 3 + c];
            }
            info[r * 6 + 5] = i2[r * 3 + 2];
            info[5 * 6 + r] = i2[2 * 3 + r];
        }
        info[2 * 6 + 2] = 1.0 / (sz * sz);
        info[3 * 6 + 3] = 1.0 / (sr * sr);
        info[4 * 6 + 4] = 1.0 / (sr * sr);
        info[5 * 6 + 5] = i2[8];
        g3.add_edge_by_index(e.from, e.to, m, info)?;
    }
    Ok(g3)
}
