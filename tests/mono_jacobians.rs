//! Analytic Jacobians of the unified camera model (eq. 2.8-2.14) against central finite
//! differences at random points over the whole field of view of pinhole, fisheye-like and
//! catadioptric models, including rays behind the image plane.

use glam::{DVec2, DVec3};
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;
use rgbid::camera::UnifiedCamera;

#[test]
fn unified_model_jacobians_match_finite_differences_at_random_points() {
    let mut rng = Pcg64::seed_from_u64(5);
    let cams = [
        UnifiedCamera::new(0.0, 300.0, 159.5, 119.5, 320, 240),
        UnifiedCamera::new(0.6, 200.0, 160.0, 120.0, 320, 240),
        UnifiedCamera::catadioptric(400, 400),
        UnifiedCamera::new(1.2, 150.0, 200.0, 200.0, 400, 400),
    ];
    let mut checked = 0;
    for cam in cams {
        for _ in 0..300 {
            let dir = DVec3::new(
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
            );
            let p = dir * rng.random_range(0.3..8.0);
            let Some(uv) = cam.project(p) else { continue };
            // Stay away from the model's boundary where a finite step leaves the domain.
            let (Some(_), Some(_)) = (
                cam.project(p + DVec3::splat(1e-3)),
                cam.project(p - DVec3::splat(1e-3)),
            ) else {
                continue;
            };
            let j = cam.project_jacobian(p);
            let h = 1e-6 * p.length();
            for k in 0..3 {
                let mut d = DVec3::ZERO;
                d[k] = h;
                let (Some(a), Some(b)) = (cam.project(p + d), cam.project(p - d)) else {
                    continue;
                };
                let num = (a - b) / (2.0 * h);
                let scale = 1.0 + num.length();
                assert!(
                    (num.x - j[0][k]).abs() < 1e-5 * scale
                        && (num.y - j[1][k]).abs() < 1e-5 * scale,
                    "project {cam:?} {p} k={k}: {num} vs ({}, {})",
                    j[0][k],
                    j[1][k]
                );
            }
            // Pixels whose lift is right at the edge of the model's domain (xi > 1:
            // 1 + (1 - xi^2) r^2 -> 0, an infinite derivative) are left out.
            let (mx, my) = ((uv.x - cam.cx) / cam.gamma, (uv.y - cam.cy) / cam.gamma);
            if 1.0 + (1.0 - cam.xi * cam.xi) * (mx * mx + my * my) < 1e-2 {
                continue;
            }
            let ju = cam.unproject_jacobian(uv);
            for k in 0..2 {
                // Richardson-extrapolated central differences: near the domain's edge
                // (xi > 1) the second derivatives are large.
                let diff = |h: f64| {
                    let mut du = DVec2::ZERO;
                    du[k] = h;
                    Some((cam.unproject(uv + du)? - cam.unproject(uv - du)?) / (2.0 * h))
                };
                let (Some(d1), Some(d2)) = (diff(1e-3), diff(5e-4)) else {
                    continue;
                };
                let num = (4.0 * d2 - d1) / 3.0;
                for r in 0..3 {
                    assert!(
                        (num[r] - ju[r][k]).abs() < 1e-6 * (1.0 + num[r].abs()),
                        "unproject {cam:?} {uv} r={r} k={k}: {} vs {}",
                        num[r],
                        ju[r][k]
                    );
                }
            }
            checked += 1;
        }
    }
    assert!(checked > 600, "only {checked} points checked");
}
