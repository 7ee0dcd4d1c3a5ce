//! Exact distances to the surface of a generated scene, for measuring reconstructions.

use glam::DVec3;

use super::scene::{Primitive, Scene, Shape};

impl Primitive {
    /// Signed distance (metres) from world point `p` to this primitive's surface: positive
    /// outside, negative inside.
    pub fn signed_distance(&self, p: DVec3) -> f64 {
        let q = self.world_from_local.transpose() * (p - self.center);
        match self.shape {
            Shape::Box { half } => {
                let d = q.abs() - half;
                d.max(DVec3::ZERO).length() + d.max_element().min(0.0)
            }
            Shape::Sphere { radius } => q.length() - radius,
            Shape::Cylinder {
                radius,
                half_height,
            } => {
                let dr = q.truncate().length() - radius;
                let dz = q.z.abs() - half_height;
                dr.max(dz).min(0.0) + glam::DVec2::new(dr.max(0.0), dz.max(0.0)).length()
            }
        }
    }
}

impl Scene {
    /// Distance (metres) from world point `p` to the scene's surface (the boundary of the
    /// union of its primitives). Exact outside every primitive; for a point inside one it is
    /// the distance to the nearest primitive surface, a lower bound where primitives overlap.
    pub fn surface_distance(&self, p: DVec3) -> f64 {
        let mut outside = f64::INFINITY;
        let mut nearest = f64::INFINITY;
        for o in self.objects() {
            for prim in &o.prims {
                let d = prim.signed_distance(p);
                outside = outside.min(d);
                nearest = nearest.min(d.abs());
            }
        }
        if outside >= 0.0 {
            outside
        } else {
            nearest
        }
    }
}

#[cfg(test)]
mod tests {
    use glam::{DMat3, DVec3};

    use super::super::scene::{Primitive, Shape};

    fn prim(shape: Shape) -> Primitive {
        Primitive {
            shape,
            center: DVec3::new(1.0, 2.0, 3.0),
            world_from_local: DMat3::from_rotation_z(0.7),
            material: 0,
            world_texture: false,
        }
    }

    #[test]
    fn primitive_distances_are_exact() {
        let c = DVec3::new(1.0, 2.0, 3.0);
        let r = DMat3::from_rotation_z(0.7);
        let b = prim(Shape::Box {
            half: DVec3::new(0.5, 0.2, 0.1),
        });
        assert!((b.signed_distance(c + r * DVec3::new(0.8, 0.0, 0.0)) - 0.3).abs() < 1e-12);
        assert!((b.signed_distance(c) + 0.1).abs() < 1e-12);
        let corner = c + r * DVec3::new(0.5 + 0.3, 0.2 + 0.4, 0.1);
        assert!((b.signed_distance(corner) - 0.5).abs() < 1e-12);
        let s = prim(Shape::Sphere { radius: 0.4 });
        assert!((s.signed_distance(c + DVec3::new(0.0, 1.0, 0.0)) - 0.6).abs() < 1e-12);
        let y = prim(Shape::Cylinder {
            radius: 0.3,
            half_height: 0.5,
        });
        assert!((y.signed_distance(c + DVec3::new(0.0, 0.0, 0.9)) - 0.4).abs() < 1e-12);
        assert!((y.signed_distance(c + DVec3::new(0.5, 0.0, 0.0)) - 0.2).abs() < 1e-12);
        assert!((y.signed_distance(c) + 0.3).abs() < 1e-12);
    }

    #[test]
    fn scene_distance_is_zero_on_rendered_surfaces() {
        let scene = crate::synth::Scene::preset("office", 3).unwrap_or_else(|e| panic!("{e}"));
        // Points on the floor seen from inside the room: z = 0 is the floor's top face.
        let area = scene.free_area();
        let p = DVec3::new(area.center().x, area.center().y, 0.0);
        assert!(
            scene.surface_distance(p) < 1e-9,
            "{}",
            scene.surface_distance(p)
        );
        let above = p + DVec3::new(0.0, 0.0, 0.05);
        let d = scene.surface_distance(above);
        assert!(d > 0.0 && d <= 0.05 + 1e-9, "{d}");
    }
}
