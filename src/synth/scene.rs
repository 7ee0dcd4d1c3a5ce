//! Procedural indoor scenes: rooms or corridors with walls (doors and windows as openings),
//! floor, ceiling, an exterior enclosure seen through the openings, furniture along the
//! walls, clutter (piles of rotated boxes, spheres, cylinders) and posters, all with
//! procedural textures. Everything is built from boxes, spheres and capped cylinders.
//!
//! World frame: z up, the floor at z = 0, the room spanning `[0, size.x] x [0, size.y]`.
//! Metres throughout.

use glam::{DMat3, DVec2, DVec3};
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;

use super::bvh::{self, Aabb};
use super::raycast::{
    pattern, Lighting, PackedMaterial, PackedPrim, PackedScene, KIND_BOX, KIND_CYLINDER,
    KIND_SPHERE,
};
use super::SynthError;

/// The shape of a primitive, in its local frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Shape {
    /// A box with these half extents (metres) along local x, y, z.
    Box {
        /// Half extents, metres.
        half: DVec3,
    },
    /// A sphere.
    Sphere {
        /// Radius, metres.
        radius: f64,
    },
    /// A capped cylinder along local z.
    Cylinder {
        /// Radius, metres.
        radius: f64,
        /// Half height, metres.
        half_height: f64,
    },
}

/// One primitive placed in the world.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Primitive {
    /// Shape in the local frame.
    pub shape: Shape,
    /// Centre in the world frame, metres.
    pub center: DVec3,
    /// Orientation, `world_from_local` rotation.
    pub world_from_local: DMat3,
    /// Index into the scene's materials.
    pub material: u32,
    /// True when the texture is anchored to the world (continuous across wall pieces);
    /// false when it moves with the primitive.
    pub world_texture: bool,
}

impl Primitive {
    fn aabb(&self) -> Aabb {
        let half = match self.shape {
            Shape::Box { half } => half,
            Shape::Sphere { radius } => DVec3::splat(radius),
            Shape::Cylinder {
                radius,
                half_height,
            } => DVec3::new(radius, radius, half_height),
        };
        let r = self.world_from_local;
        let mut e = [0.0; 3];
        for (i, ei) in e.iter_mut().enumerate() {
            *ei = (r.col(0)[i] * half.x).abs()
                + (r.col(1)[i] * half.y).abs()
                + (r.col(2)[i] * half.z).abs();
        }
        let c = self.center;
        Aabb {
            min: [c.x - e[0], c.y - e[1], c.z - e[2]],
            max: [c.x + e[0], c.y + e[1], c.z + e[2]],
        }
    }

    fn pack(&self, object: u32) -> PackedPrim {
        let (kind, p) = match self.shape {
            Shape::Box { half } => (KIND_BOX, [half.x, half.y, half.z]),
            Shape::Sphere { radius } => (KIND_SPHERE, [radius, 0.0, 0.0]),
            Shape::Cylinder {
                radius,
                half_height,
            } => (KIND_CYLINDER, [radius, half_height, 0.0]),
        };
        let r = self.world_from_local; // rows of local_from_world = columns of world_from_local
        let rows = [0, 1, 2].map(|i| {
            let c = r.col(i);
            [c.x as f32, c.y as f32, c.z as f32, p[i] as f32]
        });
        let anchor = if self.world_texture {
            r.transpose() * self.center
        } else {
            let h = super::raycast::pcg_hash(object.wrapping_mul(7919));
            DVec3::new(
                f64::from(h % 97) * 0.37,
                f64::from(h % 89) * 0.41,
                f64::from(h % 83) * 0.29,
            )
        };
        PackedPrim {
            center: [
                self.center.x as f32,
                self.center.y as f32,
                self.center.z as f32,
                f32::from_bits(kind),
            ],
            rows,
            anchor: [
                anchor.x as f32,
                anchor.y as f32,
                anchor.z as f32,
                f32::from_bits(self.material),
            ],
            extra: [f32::from_bits(object), 0.0, 0.0, 0.0],
        }
    }
}

/// What an object is (for documentation, masks and session changes).
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
pub enum ObjectKind {
    /// Walls, floor, ceiling, enclosure (id 0), never moved.
    Structure,
    /// A poster on a wall.
    Poster,
    /// Desk, shelf, cabinet, counter, bench: static furniture.
    Furniture,
    /// A chair (movable).
    Chair,
    /// A pile of small rotated boxes (movable).
    Pile,
    /// A small item on a surface: box, ball, bottle (movable).
    Item,
    /// A soft, irregular object on the floor (a bag, a heap of cushions or clothes, a
    /// potted plant), modelled as overlapping spheres: bumpy, with normals in all
    /// directions (movable).
    Soft,
}

/// A group of primitives that moves as one.
#[derive(Clone, Debug, PartialEq)]
pub struct SceneObject {
    /// Object id (0 is the static structure), written per pixel by the renderer.
    pub id: u32,
    /// What it is.
    pub kind: ObjectKind,
    /// True when sessions may move, remove or re-add it.
    pub movable: bool,
    /// Its primitives.
    pub prims: Vec<Primitive>,
}

/// The overall layout of a scene.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub enum Layout {
    /// A rectangular room; furniture along all four walls.
    Room,
    /// A long narrow corridor with doors along both long walls.
    Corridor,
}

/// Which furniture the wall walker places.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub enum FurnitureStyle {
    /// Desks with monitors and items, shelves with books, cabinets, chairs.
    Office,
    /// Counters with upper cabinets, bottles, fruit and boxes on them.
    Kitchen,
    /// Shelves, tables and many floor piles (high normal entropy).
    Lab,
    /// Benches, cabinets and sparse piles.
    Corridor,
}

/// Every parameter of the scene generator (a preset fills them; all are public).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SceneParams {
    /// Preset name (free text for custom scenes).
    pub name: String,
    /// Room or corridor.
    pub layout: Layout,
    /// Interior size: length along x, width along y, height (metres).
    pub size: [f64; 3],
    /// Number of doors (openings 0.9 x 2.05 m).
    pub doors: usize,
    /// Number of windows (openings ~1.2 x 1.1 m at 0.9 m height).
    pub windows: usize,
    /// Number of posters on the walls.
    pub posters: usize,
    /// Furniture style.
    pub style: FurnitureStyle,
    /// Probability that a wall slot gets furniture rather than staying empty.
    pub furniture_density: f64,
    /// Extra clutter piles on the floor next to the walls.
    pub piles: usize,
    /// Boxes/spheres/cylinders per pile (min, max).
    pub pile_items: (usize, usize),
    /// Soft objects (bags, cushion heaps, plants: clusters of overlapping spheres) on the
    /// floor next to the walls; sessions of scenes with soft objects also add soft objects
    /// rather than piles. 0 in the presets other than `home` (absent in older files).
    #[serde(default)]
    pub soft_objects: usize,
    /// Items per metre of furniture top surface.
    pub items_per_metre: f64,
    /// Distance kept free of furniture from each wall, used for camera paths (metres).
    pub wall_band: f64,
    /// Distance of the exterior enclosure beyond the walls (seen through openings), metres.
    pub exterior_margin: f64,
    /// Lighting direction (towards the light, world frame; normalised on use).
    pub to_light: [f64; 3],
    /// Ambient light level.
    pub ambient: f64,
    /// Diffuse light level.
    pub diffuse: f64,
    /// Walks through the scene follow an open route along its length (world x, from the
    /// low-x end towards the other) rather than a closed loop around the free area, so that a
    /// walk shorter than the route never returns to a place. True in `hall` and `stairwell`
    /// only (absent in older files).
    #[serde(default)]
    pub open_route: bool,
    /// A straight flight of stairs across the whole width, climbing towards +x; the last
    /// tread is an upper floor (a 0.2 m slab) that runs on to the far end wall. Only in
    /// `stairwell`, which is made for the `stairs` walk: other camera paths there may cross
    /// the steps (absent in older files).
    #[serde(default)]
    pub staircase: Option<Staircase>,
}

/// A straight flight of stairs across a scene's width, climbing towards world +x (metres).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Staircase {
    /// World x of the first riser, metres.
    pub first_riser_x: f64,
    /// Number of risers; the top of the last one is the upper floor.
    pub steps: usize,
    /// Height of each riser, metres.
    pub rise: f64,
    /// Depth of each tread (horizontal distance between risers), metres.
    pub run: f64,
}

impl Staircase {
    /// Height of the walking surface at world `x`, metres above the ground floor (0 before
    /// the first riser, `steps * rise` on the upper floor).
    pub fn floor_height(&self, x: f64) -> f64 {
        if x < self.first_riser_x || self.run <= 0.0 {
            return 0.0;
        }
        let k = ((x - self.first_riser_x) / self.run).floor() as usize + 1;
        k.min(self.steps) as f64 * self.rise
    }

    /// Total climb, metres.
    pub fn height(&self) -> f64 {
        self.steps as f64 * self.rise
    }
}

/// Names of the built-in presets.
pub const PRESETS: &[&str] = &[
    "office",
    "kitchen",
    "corridor",
    "lab",
    "home",
    "hall",
    "stairwell",
];

impl SceneParams {
    /// The parameters of a named preset (see [`PRESETS`]).
    pub fn preset(name: &str) -> Result<SceneParams, SynthError> {
        let base = SceneParams {
            name: name.to_string(),
            layout: Layout::Room,
            size: [6.0, 5.0, 2.7],
            doors: 1,
            windows: 1,
            posters: 4,
            style: FurnitureStyle::Office,
            furniture_density: 0.85,
            piles: 3,
            pile_items: (3, 7),
            soft_objects: 0,
            items_per_metre: 2.5,
            wall_band: 1.3,
            exterior_margin: 2.5,
            to_light: [0.35, 0.25, 0.9],
            ambient: 0.5,
            diffuse: 0.45,
            open_route: false,
            staircase: None,
        };
        // A corridor long enough for a minute's walk along it, its doors, posters and
        // furniture at the density of `corridor`.
        let long = SceneParams {
            layout: Layout::Corridor,
            size: [80.0, 3.0, 2.7],
            doors: 34,
            windows: 9,
            posters: 44,
            style: FurnitureStyle::Corridor,
            furniture_density: 0.35,
            piles: 22,
            items_per_metre: 1.0,
            wall_band: 0.95,
            open_route: true,
            ..base.clone()
        };
        Ok(match name {
            "office" => base,
            "kitchen" => SceneParams {
                size: [4.6, 4.0, 2.6],
                doors: 1,
                windows: 1,
                posters: 2,
                style: FurnitureStyle::Kitchen,
                furniture_density: 0.95,
                piles: 1,
                items_per_metre: 4.0,
                wall_band: 1.1,
                ..base
            },
            "corridor" => SceneParams {
                layout: Layout::Corridor,
                size: [18.0, 2.4, 2.6],
                doors: 8,
                windows: 2,
                posters: 10,
                style: FurnitureStyle::Corridor,
                furniture_density: 0.35,
                piles: 5,
                items_per_metre: 1.0,
                wall_band: 0.95,
                ..base
            },
            "lab" => SceneParams {
                size: [7.0, 6.0, 3.0],
                doors: 1,
                windows: 2,
                posters: 3,
                style: FurnitureStyle::Lab,
                furniture_density: 0.9,
                piles: 10,
                pile_items: (4, 10),
                items_per_metre: 3.5,
                wall_band: 1.4,
                ..base
            },
            // A lived-in room: office furniture along the walls and many soft objects
            // on the floor (the movable clutter of the thesis' changed-environment
            // recordings: bags, cushions, plants).
            "home" => SceneParams {
                size: [5.5, 4.5, 2.6],
                posters: 3,
                furniture_density: 0.7,
                piles: 2,
                soft_objects: 10,
                items_per_metre: 2.0,
                wall_band: 1.2,
                ..base
            },
            // A straight walk of about 64 m (the default pace schedule for a minute) that
            // never comes back.
            "hall" => long,
            // A hall with a flight of 12 risers of 0.17 m after 15 m; the treads are as deep
            // as a 1.75 m walker's step at 1.5 steps/s (V = alpha f^beta H of Grieve), so the
            // `stairs` walk puts one step on each. The ceiling leaves room above the upper
            // floor.
            "stairwell" => SceneParams {
                size: [70.0, 3.0, 5.0],
                doors: 26,
                windows: 7,
                posters: 36,
                piles: 16,
                staircase: Some(Staircase {
                    first_riser_x: 16.5,
                    steps: 12,
                    rise: 0.17,
                    run: 0.69,
                }),
                ..long
            },
            _ => {
                return Err(SynthError::UnknownPreset {
                    name: name.to_string(),
                    known: PRESETS.join(", "),
                });
            }
        })
    }

    /// Checks that the sizes make a usable scene.
    pub fn validate(&self) -> Result<(), SynthError> {
        let [x, y, z] = self.size;
        let ok =
            x.is_finite() && y.is_finite() && z.is_finite() && x >= 1.5 && y >= 1.5 && z >= 2.1;
        if !ok {
            return Err(SynthError::InvalidParameter {
                name: "size",
                why: format!(
                    "{:?}: need finite sizes with length, width >= 1.5 m and height >= 2.1 m",
                    self.size
                ),
            });
        }
        if !(self.wall_band > 0.0 && 2.0 * self.wall_band < x.min(y) + 0.5) {
            return Err(SynthError::InvalidParameter {
                name: "wall_band",
                why: format!(
                    "{} leaves no free space in a {x} x {y} m floor",
                    self.wall_band
                ),
            });
        }
        if let Some(st) = self.staircase {
            let ok = st.steps >= 1
                && st.rise.is_finite()
                && st.rise > 0.0
                && st.run.is_finite()
                && st.run > 0.0
                && st.first_riser_x.is_finite()
                && st.first_riser_x > 0.5
                && st.first_riser_x + st.steps as f64 * st.run < x - 0.5
                && st.height() + 2.1 <= z;
            if !ok {
                return Err(SynthError::InvalidParameter {
                    name: "staircase",
                    why: format!(
                        "{st:?}: need steps >= 1, rise and run > 0, the flight inside the \
                         {x} m length and 2.1 m of headroom above its top in the {z} m height"
                    ),
                });
            }
        }
        if self.pile_items.0 > self.pile_items.1 || self.pile_items.1 > 64 {
            return Err(SynthError::InvalidParameter {
                name: "pile_items",
                why: format!("{:?}: need min <= max <= 64", self.pile_items),
            });
        }
        Ok(())
    }
}

/// The rectangle of floor (world x, y) kept free for the camera, and the eye height range.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FreeArea {
    /// Minimum corner (x, y), metres.
    pub min: DVec2,
    /// Maximum corner (x, y), metres.
    pub max: DVec2,
    /// Ceiling height, metres.
    pub ceiling: f64,
}

impl FreeArea {
    /// Centre of the rectangle.
    pub fn center(&self) -> DVec2 {
        0.5 * (self.min + self.max)
    }
    /// Size of the rectangle.
    pub fn extent(&self) -> DVec2 {
        self.max - self.min
    }
}

/// A procedural scene: objects, materials, the packed BVH the renderers traverse, and the
/// session it belongs to (with the ids of objects changed relative to session 0).
#[derive(Clone, Debug)]
pub struct Scene {
    params: SceneParams,
    seed: u64,
    session: u32,
    objects: Vec<SceneObject>,
    materials: Vec<PackedMaterial>,
    changed: Vec<u32>,
    packed: PackedScene,
    lighting: Lighting,
}

impl Scene {
    /// A named preset (`office`, `kitchen`, `corridor`, `lab`, `home`) generated from `seed`.
    pub fn preset(name: &str, seed: u64) -> Result<Scene, SynthError> {
        Scene::generate(&SceneParams::preset(name)?, seed)
    }

    /// Generates a scene from explicit parameters.
    pub fn generate(params: &SceneParams, seed: u64) -> Result<Scene, SynthError> {
        params.validate()?;
        let mut g = Generator::new(params, seed);
        g.build();
        Ok(Scene::assemble(
            params.clone(),
            seed,
            0,
            g.objects,
            g.materials,
            Vec::new(),
        ))
    }

    fn assemble(
        params: SceneParams,
        seed: u64,
        session: u32,
        objects: Vec<SceneObject>,
        materials: Vec<PackedMaterial>,
        mut changed: Vec<u32>,
    ) -> Scene {
        let prims: Vec<(PackedPrim, Aabb)> = objects
            .iter()
            .flat_map(|o| o.prims.iter().map(move |p| (p.pack(o.id), p.aabb())))
            .collect();
        let (nodes, prims) = bvh::build(&prims);
        changed.sort_unstable();
        changed.dedup();
        let l = DVec3::from_array(params.to_light).normalize_or(DVec3::Z);
        let lighting = Lighting {
            to_light: [l.x as f32, l.y as f32, l.z as f32],
            ambient: params.ambient as f32,
            diffuse: params.diffuse as f32,
        };
        Scene {
            params,
            seed,
            session,
            objects,
            materials: materials.clone(),
            changed,
            packed: PackedScene {
                prims,
                nodes,
                materials,
            },
            lighting,
        }
    }

    /// The same scene in another session: static structure and furniture kept, movable
    /// objects moved, removed or added (deterministic in `(seed, index)`; session 0 is the
    /// scene itself). Sessions are all derived from session 0, not from each other.
    pub fn session(&self, index: u32) -> Scene {
        let base = if self.session == 0 {
            self.clone()
        } else {
            match Scene::generate(&self.params, self.seed) {
                Ok(s) => s,
                Err(_) => self.clone(),
            }
        };
        if index == 0 {
            return base;
        }
        let mut rng = Pcg64::seed_from_u64(self.seed ^ 0x5e55_1017 ^ (u64::from(index) << 32));
        let area = base.free_area();
        let mut objects = Vec::new();
        let mut changed = Vec::new();
        for o in &base.objects {
            if !o.movable {
                objects.push(o.clone());
                continue;
            }
            let r: f64 = rng.random();
            if r < 0.15 {
                changed.push(o.id); // removed: recorded, not rendered
                continue;
            }
            if r < 0.55 {
                let yaw = rng.random_range(-0.9..0.9);
                let dir = rng.random_range(0.0..std::f64::consts::TAU);
                let dist = rng.random_range(0.15..0.5);
                let mut moved = o.clone();
                let c = o.prims.iter().fold(DVec3::ZERO, |a, p| a + p.center)
                    / o.prims.len().max(1) as f64;
                let rot = DMat3::from_rotation_z(yaw);
                let shift = DVec3::new(dir.cos() * dist, dir.sin() * dist, 0.0);
                for p in &mut moved.prims {
                    p.center = c + rot * (p.center - c) + shift;
                    p.world_from_local = rot * p.world_from_local;
                }
                changed.push(o.id);
                objects.push(moved);
                continue;
            }
            objects.push(o.clone());
        }
        // Added objects: new piles next to the walls, just outside the free area.
        let mut g = Generator::new(&base.params, self.seed ^ (u64::from(index) * 0x9e37_79b9));
        g.materials = base.materials.clone();
        g.next_id = base.objects.iter().map(|o| o.id).max().unwrap_or(0) + 1000 * index;
        let added = rng.random_range(1..=3);
        for _ in 0..added {
            let side = rng.random_range(0..4);
            let t: f64 = rng.random();
            let m = 0.45;
            let (x, y) = match side {
                0 => (area.min.x + t * area.extent().x, area.min.y - m),
                1 => (area.min.x + t * area.extent().x, area.max.y + m),
                2 => (area.min.x - m, area.min.y + t * area.extent().y),
                _ => (area.max.x + m, area.min.y + t * area.extent().y),
            };
            let id = if base.params.soft_objects > 0 {
                g.soft(DVec3::new(x, y, 0.0))
            } else {
                g.pile(DVec3::new(x, y, 0.0), 0.35)
            };
            changed.push(id);
        }
        objects.extend(g.objects);
        Scene::assemble(
            base.params.clone(),
            self.seed,
            index,
            objects,
            g.materials,
            changed,
        )
    }

    /// The generator parameters.
    pub fn params(&self) -> &SceneParams {
        &self.params
    }
    /// The seed the scene was generated from.
    pub fn seed(&self) -> u64 {
        self.seed
    }
    /// Session index (0 = the reference arrangement).
    pub fn session_index(&self) -> u32 {
        self.session
    }
    /// All objects (structure first).
    pub fn objects(&self) -> &[SceneObject] {
        &self.objects
    }
    /// Ids of objects moved, removed or added relative to session 0 (sorted).
    pub fn changed_objects(&self) -> &[u32] {
        &self.changed
    }
    /// Number of primitives.
    pub fn primitive_count(&self) -> usize {
        self.packed.prims.len()
    }
    /// The packed f32 scene (primitives, BVH nodes, materials) the ray casters read.
    pub fn packed(&self) -> &PackedScene {
        &self.packed
    }
    /// The lighting.
    pub fn lighting(&self) -> &Lighting {
        &self.lighting
    }
    /// The floor rectangle kept free for camera paths.
    pub fn free_area(&self) -> FreeArea {
        let [x, y, z] = self.params.size;
        let b = self.params.wall_band;
        match self.params.layout {
            Layout::Room => FreeArea {
                min: DVec2::new(b, b),
                max: DVec2::new(x - b, y - b),
                ceiling: z,
            },
            Layout::Corridor => FreeArea {
                min: DVec2::new(1.0, b.min(y * 0.5 - 0.1)),
                max: DVec2::new(x - 1.0, (y - b).max(y * 0.5 + 0.1)),
                ceiling: z,
            },
        }
    }
}

/// Builds objects and materials.
struct Generator<'a> {
    p: &'a SceneParams,
    rng: Pcg64,
    objects: Vec<SceneObject>,
    materials: Vec<PackedMaterial>,
    next_id: u32,
}

/// A wall of the room: origin at its start (floor level, interior face), direction along
/// it, inward normal.
#[derive(Clone, Copy)]
struct Wall {
    origin: DVec3,
    dir: DVec3,
    inward: DVec3,
    length: f64,
}

impl Wall {
    fn frame(&self) -> DMat3 {
        DMat3::from_cols(self.dir, self.inward, DVec3::Z)
    }
    fn point(&self, u: f64, depth: f64, z: f64) -> DVec3 {
        self.origin + self.dir * u + self.inward * depth + DVec3::Z * z
    }
}

impl<'a> Generator<'a> {
    fn new(p: &'a SceneParams, seed: u64) -> Self {
        Generator {
            p,
            rng: Pcg64::seed_from_u64(seed),
            objects: Vec::new(),
            materials: Vec::new(),
            next_id: 1,
        }
    }

    fn color(&mut self, lo: f32, hi: f32) -> [f32; 3] {
        let base: f32 = self.rng.random_range(lo..hi);
        let tint = [
            self.rng.random_range(-0.25..0.25f32),
            self.rng.random_range(-0.25..0.25f32),
        ];
        [
            (base + tint[0]).clamp(0.02, 1.0),
            base.clamp(0.02, 1.0),
            (base + tint[1]).clamp(0.02, 1.0),
        ]
    }

    /// Adds a material with two contrasting colours; returns its index.
    fn material(&mut self, kind: u32, scale: f32, specular: f32) -> u32 {
        let c0 = self.color(0.15, 0.45);
        let c1 = self.color(0.55, 0.95);
        let seed: u32 = self.rng.random();
        self.materials.push(PackedMaterial {
            color0: [c0[0], c0[1], c0[2], f32::from_bits(kind)],
            color1: [c1[0], c1[1], c1[2], scale],
            params: [f32::from_bits(seed), specular, 0.3, 0.0],
        });
        (self.materials.len() - 1) as u32
    }

    fn random_material(&mut self, small: bool) -> u32 {
        let kind = [
            pattern::NOISE,
            pattern::STRIPES,
            pattern::CHECKER,
            pattern::POSTER,
            pattern::GRAIN,
        ][self.rng.random_range(0..5)];
        let scale = if small {
            self.rng.random_range(0.04..0.12)
        } else {
            self.rng.random_range(0.12..0.5)
        };
        let spec = self.rng.random_range(0.0..0.12);
        self.material(kind, scale, spec)
    }

    fn push_object(&mut self, kind: ObjectKind, movable: bool, prims: Vec<Primitive>) -> u32 {
        let id = if kind == ObjectKind::Structure {
            0
        } else {
            self.next_id
        };
        if kind != ObjectKind::Structure {
            self.next_id += 1;
        }
        self.objects.push(SceneObject {
            id,
            kind,
            movable,
            prims,
        });
        id
    }

    fn boxp(center: DVec3, half: DVec3, rot: DMat3, material: u32) -> Primitive {
        Primitive {
            shape: Shape::Box { half },
            center,
            world_from_local: rot,
            material,
            world_texture: false,
        }
    }

    fn build(&mut self) {
        let [sx, sy, sz] = self.p.size;
        let m = self.p.exterior_margin;
        let floor_kind = match self.p.style {
            FurnitureStyle::Kitchen => pattern::CHECKER,
            FurnitureStyle::Office => pattern::GRAIN,
            _ => pattern::NOISE,
        };
        let floor_scale = if floor_kind == pattern::CHECKER {
            0.3
        } else {
            0.35
        };
        let floor_mat = self.material(floor_kind, floor_scale, 0.05);
        let ceil_mat = self.material(pattern::NOISE, 0.25, 0.0);
        let wall_mat = self.material(pattern::NOISE, 0.2, 0.02);
        let wall2_mat = self.material(pattern::STRIPES, 0.15, 0.02);
        let ext_mat = self.material(pattern::POSTER, 0.6, 0.0);
        let mut s = Vec::new();
        let wt = |mut p: Primitive| {
            p.world_texture = true;
            p
        };
        let id = DMat3::IDENTITY;
        // Floor and ceiling slabs span the exterior enclosure.
        let cx = sx * 0.5;
        let cy = sy * 0.5;
        let hx = sx * 0.5 + m + 0.2;
        let hy = sy * 0.5 + m + 0.2;
        s.push(wt(Self::boxp(
            DVec3::new(cx, cy, -0.05),
            DVec3::new(hx, hy, 0.05),
            id,
            floor_mat,
        )));
        s.push(wt(Self::boxp(
            DVec3::new(cx, cy, sz + 0.05),
            DVec3::new(hx, hy, 0.05),
            id,
            ceil_mat,
        )));
        // Exterior enclosure walls.
        for (c, h) in [
            (
                DVec3::new(cx, -m - 0.1, sz * 0.5),
                DVec3::new(hx, 0.1, sz * 0.5),
            ),
            (
                DVec3::new(cx, sy + m + 0.1, sz * 0.5),
                DVec3::new(hx, 0.1, sz * 0.5),
            ),
            (
                DVec3::new(-m - 0.1, cy, sz * 0.5),
                DVec3::new(0.1, hy, sz * 0.5),
            ),
            (
                DVec3::new(sx + m + 0.1, cy, sz * 0.5),
                DVec3::new(0.1, hy, sz * 0.5),
            ),
        ] {
            s.push(wt(Self::boxp(c, h, id, ext_mat)));
        }
        let walls = [
            Wall {
                origin: DVec3::new(0.0, 0.0, 0.0),
                dir: DVec3::X,
                inward: DVec3::Y,
                length: sx,
            },
            Wall {
                origin: DVec3::new(sx, sy, 0.0),
                dir: -DVec3::X,
                inward: -DVec3::Y,
                length: sx,
            },
            Wall {
                origin: DVec3::new(0.0, sy, 0.0),
                dir: -DVec3::Y,
                inward: DVec3::X,
                length: sy,
            },
            Wall {
                origin: DVec3::new(sx, 0.0, 0.0),
                dir: DVec3::Y,
                inward: -DVec3::X,
                length: sy,
            },
        ];
        // Openings per wall: (u0, u1, z0, z1).
        let mut openings: Vec<Vec<(f64, f64, f64, f64)>> = vec![Vec::new(); 4];
        let long_walls: Vec<usize> = if self.p.layout == Layout::Corridor {
            vec![0, 1]
        } else {
            vec![0, 1, 2, 3]
        };
        for k in 0..self.p.doors + self.p.windows {
            let is_door = k < self.p.doors;
            let w = if is_door {
                0.9
            } else {
                self.rng.random_range(1.0..1.5)
            };
            let (z0, z1) = if is_door {
                (0.0, 2.05)
            } else {
                (0.9, (0.9 + 1.1f64).min(sz - 0.3))
            };
            for _attempt in 0..20 {
                let wi = long_walls[self.rng.random_range(0..long_walls.len())];
                let len = walls[wi].length;
                if len < w + 0.8 {
                    continue;
                }
                let u0 = self.rng.random_range(0.4..len - w - 0.4);
                let clash = openings[wi]
                    .iter()
                    .any(|o| u0 < o.1 + 0.5 && u0 + w > o.0 - 0.5);
                if !clash {
                    openings[wi].push((u0, u0 + w, z0, z1));
                    break;
                }
            }
        }
        let t = 0.1; // wall thickness
        for (wi, wall) in walls.iter().enumerate() {
            let mat = if wi % 2 == 0 { wall_mat } else { wall2_mat };
            let mut ops = openings[wi].clone();
            ops.sort_by(|a, b| a.0.total_cmp(&b.0));
            // Extend walls by the thickness at both ends so the corners close.
            let mut pieces: Vec<(f64, f64, f64, f64)> = Vec::new();
            let mut u = -t;
            for &(u0, u1, z0, z1) in &ops {
                pieces.push((u, u0, 0.0, sz));
                if z0 > 0.0 {
                    pieces.push((u0, u1, 0.0, z0));
                }
                pieces.push((u0, u1, z1, sz));
                u = u1;
            }
            pieces.push((u, wall.length + t, 0.0, sz));
            let rot = wall.frame();
            for (a, b, z0, z1) in pieces {
                if b - a < 1e-3 || z1 - z0 < 1e-3 {
                    continue;
                }
                let c = wall.point(0.5 * (a + b), -0.5 * t, 0.5 * (z0 + z1));
                s.push(wt(Self::boxp(
                    c,
                    DVec3::new(0.5 * (b - a), 0.5 * t, 0.5 * (z1 - z0)),
                    rot,
                    mat,
                )));
            }
        }
        self.push_object(ObjectKind::Structure, false, s);
        // Posters.
        for _ in 0..self.p.posters {
            let wi = long_walls[self.rng.random_range(0..long_walls.len())];
            let wall = walls[wi];
            let w = self.rng.random_range(0.4..1.1);
            let h = self.rng.random_range(0.4..0.9);
            if wall.length < w + 0.4 {
                continue;
            }
            let u = self
                .rng
                .random_range(0.2 + w * 0.5..wall.length - 0.2 - w * 0.5);
            let z = self.rng.random_range(1.2f64..1.9).min(sz - h * 0.5 - 0.1);
            let clash = openings[wi]
                .iter()
                .any(|o| u + w * 0.5 > o.0 - 0.1 && u - w * 0.5 < o.1 + 0.1);
            if clash {
                continue;
            }
            let scale = self.rng.random_range(0.08..0.2);
            let mat = self.material(pattern::POSTER, scale, 0.1);
            let c = wall.point(u, 0.006, z);
            let p = Self::boxp(c, DVec3::new(w * 0.5, 0.005, h * 0.5), wall.frame(), mat);
            self.push_object(ObjectKind::Poster, false, vec![p]);
        }
        // Furniture along the walls, skipping doors.
        for (wi, wall) in walls.iter().enumerate() {
            let mut u = self.rng.random_range(0.05..0.4);
            while u < wall.length - 0.4 {
                let w = self
                    .rng
                    .random_range(0.6..1.5f64)
                    .min(wall.length - u - 0.05);
                if w < 0.4 {
                    break;
                }
                let blocked = openings[wi]
                    .iter()
                    .any(|o| o.2 < 0.5 && u < o.1 + 0.1 && u + w > o.0 - 0.1);
                if !blocked
                    && self
                        .rng
                        .random_bool(self.p.furniture_density.clamp(0.0, 1.0))
                {
                    self.furniture(wall, u, w);
                }
                u += w + self.rng.random_range(0.05..0.4);
            }
        }
        // Floor piles in the band next to the walls.
        for _ in 0..self.p.piles {
            let wall = walls[long_walls[self.rng.random_range(0..long_walls.len())]];
            let u = self.rng.random_range(0.4..wall.length - 0.4);
            let band = if self.p.layout == Layout::Corridor {
                0.35
            } else {
                (self.p.wall_band - 0.35).max(0.3)
            };
            let d = self.rng.random_range(0.25..band.max(0.26));
            let c = wall.point(u, d, 0.0);
            self.pile(c, 0.3);
        }
        // Soft objects in the same band.
        for _ in 0..self.p.soft_objects {
            let wall = walls[long_walls[self.rng.random_range(0..long_walls.len())]];
            let u = self.rng.random_range(0.4..wall.length - 0.4);
            let band = (self.p.wall_band - 0.3).max(0.3);
            let d = self.rng.random_range(0.25..band.max(0.26));
            let c = wall.point(u, d, 0.0);
            self.soft(c);
        }
        if let Some(st) = self.p.staircase {
            self.staircase(&st);
        }
    }

    /// Adds the flight of stairs to the structure (solid boxes across the width, then the
    /// upper floor, a slab up to the far end wall) and stands the other objects on the
    /// surface below them: lifted by the floor height under them, or left out where they
    /// would straddle a riser.
    fn staircase(&mut self, st: &Staircase) {
        let [sx, sy, _] = self.p.size;
        let mat = self.material(pattern::NOISE, 0.2, 0.03);
        let mut steps = Vec::with_capacity(st.steps);
        for k in 0..st.steps {
            let x0 = st.first_riser_x + k as f64 * st.run;
            let x1 = if k + 1 == st.steps { sx } else { x0 + st.run };
            let h = (k + 1) as f64 * st.rise;
            // The upper floor is a slab, leaving a low storey under it rather than a solid
            // block that a camera placed at the scene's centre would sit inside.
            let z0 = if k + 1 == st.steps {
                (h - 0.2).max(0.0)
            } else {
                0.0
            };
            let mut p = Self::boxp(
                DVec3::new(0.5 * (x0 + x1), 0.5 * sy, 0.5 * (z0 + h)),
                DVec3::new(0.5 * (x1 - x0), 0.5 * sy, 0.5 * (h - z0)),
                DMat3::IDENTITY,
                mat,
            );
            p.world_texture = true;
            steps.push(p);
        }
        let mut kept = Vec::with_capacity(self.objects.len());
        for mut o in std::mem::take(&mut self.objects) {
            if o.kind == ObjectKind::Structure {
                o.prims.extend(steps.iter().copied());
                kept.push(o);
                continue;
            }
            let (lo, hi) = o.prims.iter().fold((f64::MAX, f64::MIN), |(lo, hi), p| {
                let b = p.aabb();
                (lo.min(b.min[0]), hi.max(b.max[0]))
            });
            let (z0, z1) = (st.floor_height(lo), st.floor_height(hi));
            if z0 != z1 {
                continue;
            }
            for p in &mut o.prims {
                p.center.z += z0;
            }
            kept.push(o);
        }
        self.objects = kept;
    }

    /// One piece of furniture of the style at wall position `u` of width `w`.
    fn furniture(&mut self, wall: &Wall, u: f64, w: f64) {
        let rot = wall.frame();
        let style = self.p.style;
        let pick: u32 = self.rng.random_range(0..100);
        let sz = self.p.size[2];
        let body = self.random_material(false);
        let second = self.random_material(false);
        let mut prims = Vec::new();
        let mut top_z = None;
        let mid = u + w * 0.5;
        match (style, pick) {
            (FurnitureStyle::Office, 0..=44) | (FurnitureStyle::Lab, 0..=39) => {
                // Desk: top, two side panels, modesty panel.
                let d = 0.7;
                let h = 0.74;
                prims.push(Self::boxp(
                    wall.point(mid, d * 0.5, h - 0.015),
                    DVec3::new(w * 0.5, d * 0.5, 0.015),
                    rot,
                    body,
                ));
                for s in [-1.0, 1.0] {
                    prims.push(Self::boxp(
                        wall.point(mid + s * (w * 0.5 - 0.02), d * 0.5, (h - 0.03) * 0.5),
                        DVec3::new(0.02, d * 0.5 - 0.02, (h - 0.03) * 0.5),
                        rot,
                        second,
                    ));
                }
                prims.push(Self::boxp(
                    wall.point(mid, 0.1, h * 0.55),
                    DVec3::new(w * 0.5 - 0.04, 0.01, h * 0.2),
                    rot,
                    second,
                ));
                top_z = Some((h, d));
                if style == FurnitureStyle::Office {
                    // Monitor on the desk (part of the desk object).
                    let screen = self.material(pattern::POSTER, 0.05, 0.2);
                    let mw = (w * 0.4).min(0.6);
                    prims.push(Self::boxp(
                        wall.point(mid, 0.2, h + 0.3),
                        DVec3::new(mw * 0.5, 0.02, 0.18),
                        rot,
                        screen,
                    ));
                    prims.push(Self::boxp(
                        wall.point(mid, 0.22, h + 0.06),
                        DVec3::new(0.03, 0.03, 0.06),
                        rot,
                        second,
                    ));
                    // A chair in front (movable).
                    self.chair(wall, mid, d + 0.25);
                }
            }
            (FurnitureStyle::Kitchen, _) => {
                // Counter with doors, worktop, upper cabinet.
                let d = 0.6;
                let h = 0.9;
                prims.push(Self::boxp(
                    wall.point(mid, d * 0.5 - 0.02, (h - 0.04) * 0.5),
                    DVec3::new(w * 0.5, d * 0.5 - 0.02, (h - 0.04) * 0.5),
                    rot,
                    body,
                ));
                prims.push(Self::boxp(
                    wall.point(mid, d * 0.5, h - 0.02),
                    DVec3::new(w * 0.5, d * 0.5, 0.02),
                    rot,
                    second,
                ));
                let handle = self.material(pattern::NOISE, 0.05, 0.3);
                let doors = (w / 0.5).floor().max(1.0) as usize;
                for k in 0..doors {
                    let du = u + (k as f64 + 0.5) * w / doors as f64;
                    prims.push(Self::boxp(
                        wall.point(du, d - 0.03, h - 0.2),
                        DVec3::new(0.06, 0.012, 0.012),
                        rot,
                        handle,
                    ));
                }
                if sz > 2.3 && pick < 80 {
                    let top = (sz - 0.1).min(2.25);
                    let ud = 0.35;
                    prims.push(Self::boxp(
                        wall.point(mid, ud * 0.5, (1.5 + top) * 0.5),
                        DVec3::new(w * 0.5, ud * 0.5, (top - 1.5) * 0.5),
                        rot,
                        second,
                    ));
                }
                top_z = Some((h, d));
            }
            (FurnitureStyle::Corridor, 0..=49) => {
                // Bench.
                let d = 0.4;
                let h = 0.45;
                prims.push(Self::boxp(
                    wall.point(mid, d * 0.5, h - 0.03),
                    DVec3::new(w * 0.5, d * 0.5, 0.03),
                    rot,
                    body,
                ));
                for s in [-1.0, 1.0] {
                    prims.push(Self::boxp(
                        wall.point(mid + s * (w * 0.5 - 0.05), d * 0.5, (h - 0.06) * 0.5),
                        DVec3::new(0.03, d * 0.5 - 0.03, (h - 0.06) * 0.5),
                        rot,
                        second,
                    ));
                }
                top_z = Some((h, d));
            }
            (_, p) if p < 75 => {
                // Shelf with books.
                let d = 0.35;
                let h = self.rng.random_range(1.5f64..2.1).min(sz - 0.2);
                let boards = 4;
                prims.push(Self::boxp(
                    wall.point(mid, 0.01, h * 0.5),
                    DVec3::new(w * 0.5, 0.01, h * 0.5),
                    rot,
                    second,
                ));
                for s in [-1.0, 1.0] {
                    prims.push(Self::boxp(
                        wall.point(mid + s * (w * 0.5 - 0.015), d * 0.5, h * 0.5),
                        DVec3::new(0.015, d * 0.5, h * 0.5),
                        rot,
                        body,
                    ));
                }
                for k in 0..=boards {
                    let z = 0.05 + (h - 0.07) * k as f64 / boards as f64;
                    prims.push(Self::boxp(
                        wall.point(mid, d * 0.5, z),
                        DVec3::new(w * 0.5 - 0.03, d * 0.5, 0.015),
                        rot,
                        body,
                    ));
                    if k < boards {
                        // A row of books, slightly tilted, varying sizes.
                        let mut bu = u + 0.04;
                        let shelf_h = (h - 0.07) / boards as f64 - 0.03;
                        while bu < u + w - 0.08 {
                            let bw = self.rng.random_range(0.02..0.06);
                            let bh = self.rng.random_range(0.5..0.95) * shelf_h;
                            let bd = self.rng.random_range(0.15..0.3);
                            let tilt = DMat3::from_rotation_y(self.rng.random_range(-0.12..0.12));
                            let mat = self.random_material(true);
                            if self.rng.random_bool(0.85) {
                                prims.push(Self::boxp(
                                    wall.point(
                                        bu + bw * 0.5,
                                        bd * 0.5 + 0.03,
                                        z + 0.015 + bh * 0.5,
                                    ),
                                    DVec3::new(bw * 0.5, bd * 0.5, bh * 0.5),
                                    rot * tilt,
                                    mat,
                                ));
                            }
                            bu += bw + 0.004;
                        }
                    }
                }
            }
            _ => {
                // Cabinet with a handle.
                let d = 0.5;
                let h = self.rng.random_range(0.75..1.25);
                prims.push(Self::boxp(
                    wall.point(mid, d * 0.5, h * 0.5),
                    DVec3::new(w * 0.5, d * 0.5, h * 0.5),
                    rot,
                    body,
                ));
                let handle = self.material(pattern::NOISE, 0.05, 0.3);
                prims.push(Self::boxp(
                    wall.point(mid, d + 0.015, h * 0.75),
                    DVec3::new(0.01, 0.015, 0.08),
                    rot,
                    handle,
                ));
                top_z = Some((h, d));
            }
        }
        self.push_object(ObjectKind::Furniture, false, prims);
        if let Some((h, d)) = top_z {
            let n = (self.p.items_per_metre * w).round() as usize;
            for _ in 0..n {
                let iu = self.rng.random_range(u + 0.08..u + w - 0.08);
                let id = self.rng.random_range(0.08..d - 0.08);
                self.item(wall.point(iu, id, h), rot);
            }
        }
    }

    fn chair(&mut self, wall: &Wall, u: f64, depth: f64) {
        let yaw = DMat3::from_rotation_z(self.rng.random_range(-0.5..0.5));
        let rot = wall.frame() * yaw;
        let c = wall.point(u, depth, 0.0);
        let mat = self.random_material(false);
        let leg = self.material(pattern::NOISE, 0.05, 0.2);
        let mut p = vec![Self::boxp(
            c + DVec3::Z * 0.46,
            DVec3::new(0.22, 0.22, 0.03),
            rot,
            mat,
        )];
        // Back rest on the far side from the desk (local +y).
        p.push(Self::boxp(
            c + rot * DVec3::new(0.0, 0.2, 0.75),
            DVec3::new(0.2, 0.02, 0.25),
            rot,
            mat,
        ));
        for (sx, sy) in [(-1.0, -1.0), (1.0, -1.0), (-1.0, 1.0), (1.0, 1.0)] {
            let lc = c + rot * DVec3::new(sx * 0.18, sy * 0.18, 0.215);
            p.push(Primitive {
                shape: Shape::Cylinder {
                    radius: 0.018,
                    half_height: 0.215,
                },
                center: lc,
                world_from_local: rot,
                material: leg,
                world_texture: false,
            });
        }
        self.push_object(ObjectKind::Chair, true, p);
    }

    /// A random small item standing on a surface at `base` (z = surface height).
    fn item(&mut self, base: DVec3, rot: DMat3) -> u32 {
        let mat = self.random_material(true);
        let kind: u32 = self.rng.random_range(0..3);
        let yaw = DMat3::from_rotation_z(self.rng.random_range(0.0..std::f64::consts::TAU));
        let p = match kind {
            0 => {
                let h = DVec3::new(
                    self.rng.random_range(0.03..0.12),
                    self.rng.random_range(0.03..0.1),
                    self.rng.random_range(0.02..0.12),
                );
                Self::boxp(base + DVec3::Z * h.z, h, rot * yaw, mat)
            }
            1 => {
                let r = self.rng.random_range(0.03..0.08);
                Primitive {
                    shape: Shape::Sphere { radius: r },
                    center: base + DVec3::Z * r,
                    world_from_local: yaw,
                    material: mat,
                    world_texture: false,
                }
            }
            _ => {
                let r = self.rng.random_range(0.025..0.05);
                let hh = self.rng.random_range(0.05..0.15);
                Primitive {
                    shape: Shape::Cylinder {
                        radius: r,
                        half_height: hh,
                    },
                    center: base + DVec3::Z * hh,
                    world_from_local: yaw,
                    material: mat,
                    world_texture: false,
                }
            }
        };
        self.push_object(ObjectKind::Item, true, vec![p])
    }

    /// A soft object standing on the floor at `c`: overlapping spheres of 4-14 cm radius
    /// within a footprint of 15-35 cm, stacked 0.3-1.4 m high (about 10 spheres per 40 cm
    /// of height, so the surface stays closed), in one or two materials: a bag or a heap of
    /// cushions when low, a coat stand or a plant when tall (seen from eye height).
    fn soft(&mut self, c: DVec3) -> u32 {
        let height = self.rng.random_range(0.3..1.4f64);
        let n = (8.0 + height * 25.0).round() as usize;
        let foot = self.rng.random_range(0.15..0.35);
        let mats = [self.random_material(true), self.random_material(true)];
        let prims = (0..n)
            .map(|_| {
                let a = self.rng.random_range(0.0..std::f64::consts::TAU);
                let rr = foot * self.rng.random::<f64>().sqrt();
                let r = self.rng.random_range(0.04..0.14f64);
                // Lower spheres spread wider, upper ones sit nearer the axis.
                let h = self.rng.random_range(0.0..1.0f64);
                let spread = 1.0 - 0.4 * h;
                Primitive {
                    shape: Shape::Sphere { radius: r },
                    center: c
                        + DVec3::new(a.cos() * rr * spread, a.sin() * rr * spread, 0.0)
                        + DVec3::Z * (r.min(height) + h * (height - r).max(0.0)),
                    world_from_local: DMat3::from_rotation_z(a),
                    material: mats[self.rng.random_range(0..2)],
                    world_texture: false,
                }
            })
            .collect();
        self.push_object(ObjectKind::Soft, true, prims)
    }

    /// A pile of rotated boxes, spheres and cylinders around floor point `c` within `radius`.
    fn pile(&mut self, c: DVec3, radius: f64) -> u32 {
        let (lo, hi) = self.p.pile_items;
        let n = self.rng.random_range(lo..=hi.max(lo));
        let mut prims = Vec::new();
        let mut top = 0.0f64;
        for k in 0..n {
            let mat = self.random_material(true);
            let off = DVec3::new(
                self.rng.random_range(-radius..radius),
                self.rng.random_range(-radius..radius),
                0.0,
            );
            let rot = DMat3::from_rotation_z(self.rng.random_range(0.0..std::f64::consts::TAU))
                * DMat3::from_rotation_x(self.rng.random_range(-0.35..0.35))
                * DMat3::from_rotation_y(self.rng.random_range(-0.35..0.35));
            let z = if k == 0 {
                0.0
            } else {
                self.rng.random_range(0.0..top.max(0.01))
            };
            let kind: u32 = self.rng.random_range(0..10);
            let p = if kind < 6 {
                let h = DVec3::new(
                    self.rng.random_range(0.05..0.2),
                    self.rng.random_range(0.05..0.2),
                    self.rng.random_range(0.04..0.16),
                );
                top = top.max(z + 2.0 * h.z);
                Self::boxp(c + off + DVec3::Z * (z + h.z), h, rot, mat)
            } else if kind < 8 {
                let r = self.rng.random_range(0.05..0.14);
                top = top.max(z + 2.0 * r);
                Primitive {
                    shape: Shape::Sphere { radius: r },
                    center: c + off + DVec3::Z * (z + r),
                    world_from_local: rot,
                    material: mat,
                    world_texture: false,
                }
            } else {
                let r = self.rng.random_range(0.04..0.1);
                let hh = self.rng.random_range(0.08..0.25);
                top = top.max(z + 2.0 * hh);
                Primitive {
                    shape: Shape::Cylinder {
                        radius: r,
                        half_height: hh,
                    },
                    center: c + off + DVec3::Z * (z + hh),
                    world_from_local: rot,
                    material: mat,
                    world_texture: false,
                }
            };
            prims.push(p);
        }
        self.push_object(ObjectKind::Pile, true, prims)
    }
}
