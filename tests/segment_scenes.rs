//! Superjut segmentation on analytic scenes: inverse depth is ray-cast exactly (ray-plane,
//! ray-sphere and ray-box intersections), so the geometry is known without a renderer.

use rand::{Rng, SeedableRng};
use rgbid::camera::PinholeCamera;
use rgbid::image::ImageF32;
use rgbid::segment::{self, SegmentConfig, Segmenter, SphereBins, Superjuts, NO_SEGMENT};

const W: usize = 160;
const H: usize = 120;

fn camera() -> PinholeCamera {
    PinholeCamera::new(130.0, 130.0, 79.5, 59.5, W as u32, H as u32)
}

/// Scene primitives in the camera frame (metres).
enum Prim {
    /// Plane `n . p = d`.
    Plane([f64; 3], f64),
    /// Sphere centre, radius.
    Sphere([f64; 3], f64),
    /// Axis-aligned box min, max.
    Box([f64; 3], [f64; 3]),
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// Depth `z` (metres) of the first hit along the ray `(x, y, 1) t`, if any.
fn hit(p: &Prim, d: [f64; 3]) -> Option<f64> {
    match p {
        Prim::Plane(n, dist) => {
            let den = dot(*n, d);
            (den.abs() > 1e-12).then(|| dist / den).filter(|t| *t > 0.0)
        }
        Prim::Sphere(c, r) => {
            let a = dot(d, d);
            let b = -2.0 * dot(d, *c);
            let cc = dot(*c, *c) - r * r;
            let disc = b * b - 4.0 * a * cc;
            (disc >= 0.0)
                .then(|| (-b - disc.sqrt()) / (2.0 * a))
                .filter(|t| *t > 0.0)
        }
        Prim::Box(lo, hi) => {
            let (mut t0, mut t1) = (0.0f64, f64::INFINITY);
            for k in 0..3 {
                if d[k].abs() < 1e-15 {
                    if !(lo[k]..=hi[k]).contains(&0.0) {
                        return None;
                    }
                    continue;
                }
                let (a, b) = ((lo[k]) / d[k], (hi[k]) / d[k]);
                t0 = t0.max(a.min(b));
                t1 = t1.min(a.max(b));
            }
            (t0 <= t1 && t0 > 0.0).then_some(t0)
        }
    }
}

/// Inverse-depth image of a scene, with optional multiplicative noise on depth.
fn render(scene: &[Prim], noise: f64, seed: u64) -> ImageF32 {
    let cam = camera();
    let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
    let mut img = ImageF32::filled(W, H, 0.0);
    for v in 0..H {
        for u in 0..W {
            let d = [
                (u as f64 - cam.cx) / cam.fx,
                (v as f64 - cam.cy) / cam.fy,
                1.0,
            ];
            if let Some(z) = scene
                .iter()
                .filter_map(|p| hit(p, d))
                .min_by(f64::total_cmp)
            {
                let n: f64 = if noise > 0.0 {
                    rng.random_range(-1.0..1.0) * noise * 1.7320508
                } else {
                    0.0
                };
                img.data_mut()[v * W + u] = (1.0 / (z * (1.0 + n))) as f32;
            }
        }
    }
    img
}

fn textured() -> ImageF32 {
    let mut img = ImageF32::filled(W, H, 0.0);
    for (i, v) in img.data_mut().iter_mut().enumerate() {
        *v = ((i * 37 % 101) as f32) * 2.0;
    }
    img
}

fn run(scene: &[Prim]) -> Superjuts {
    segment::segment_keyframe(
        &textured(),
        &render(scene, 0.0, 1),
        &camera(),
        &SegmentConfig::default(),
    )
    .unwrap()
}

fn label_at(s: &Superjuts, u: usize, v: usize) -> u32 {
    s.labels[v * s.width + u]
}

/// A floor seen obliquely: normal tilted 40 degrees from the optical axis.
fn tilted_plane() -> Prim {
    let a = 40f64.to_radians();
    Prim::Plane([0.0, -a.sin(), -a.cos()], -2.0)
}

#[test]
fn plane_is_one_segment_with_near_zero_entropy() {
    let s = run(&[tilted_plane()]);
    assert_eq!(s.segments.len(), 1, "a plane must be one superjut");
    let j = &s.segments[0];
    assert!(j.size as f64 > 0.98 * (W * H) as f64, "size {}", j.size);
    assert!(j.entropy < 0.05, "entropy {}", j.entropy);
    assert!(j.neg_entropy > 0.98, "neg-entropy {}", j.neg_entropy);
    assert!(j.planarity > 0.999, "planarity {}", j.planarity);
    let pn = j.plane_normal;
    let a = 40f64.to_radians();
    assert!(
        (pn[1] + a.sin()).abs() < 1e-3 && (pn[2] + a.cos()).abs() < 1e-3,
        "plane normal {pn:?}"
    );
}

#[test]
fn noisy_plane_stays_one_dominant_low_entropy_segment() {
    // 0.3 % depth noise (uniform, std): about what a Kinect gives at 1 m.
    let rho = render(&[tilted_plane()], 0.003, 7);
    let s =
        segment::segment_keyframe(&textured(), &rho, &camera(), &SegmentConfig::default()).unwrap();
    let big = s.segments.iter().max_by_key(|j| j.size).unwrap();
    let valid = s.labels.iter().filter(|&&l| l != NO_SEGMENT).count();
    println!(
        "noisy plane: {} segments, largest {} of {valid}, neg-entropy {:.3}",
        s.segments.len(),
        big.size,
        big.neg_entropy
    );
    assert!(big.size as f64 > 0.9 * valid as f64);
    assert!(big.neg_entropy > 0.6, "neg-entropy {}", big.neg_entropy);
}

#[test]
fn sphere_has_high_entropy_and_the_wall_behind_low() {
    let wall = Prim::Plane([0.0, 0.0, -1.0], -3.0);
    let sphere = Prim::Sphere([0.0, 0.0, 1.5], 0.4);
    let s = run(&[wall, sphere]);
    let sj = &s.segments[label_at(&s, 80, 60) as usize];
    let wj = &s.segments[label_at(&s, 5, 5) as usize];
    println!(
        "sphere: H = {:.3} neg = {:.3} planarity {:.3}; wall: neg = {:.3}",
        sj.entropy, sj.neg_entropy, sj.planarity, wj.neg_entropy
    );
    assert_ne!(sj.label, wj.label);
    assert!(
        sj.neg_entropy < 0.45,
        "sphere neg-entropy {}",
        sj.neg_entropy
    );
    assert!(sj.entropy > 2.0, "sphere entropy {}", sj.entropy);
    assert!(wj.neg_entropy > 0.98, "wall neg-entropy {}", wj.neg_entropy);
    assert!(sj.planarity < 0.9 && wj.planarity > 0.999);
    // Masks: the wall survives a 0.8 threshold, the sphere does not.
    let m = s.mask(0.8);
    assert!(m.keep(5, 5) && !m.keep(80, 60));
}

#[test]
fn clutter_has_higher_entropy_than_the_wall() {
    // A pile of interpenetrating spheres in front of a wall.
    let mut scene = vec![Prim::Plane([0.0, 0.0, -1.0], -3.0)];
    let mut rng = rand_pcg::Pcg64::seed_from_u64(3);
    for _ in 0..14 {
        let c = [
            rng.random_range(-0.4..0.4),
            rng.random_range(-0.3..0.3),
            rng.random_range(1.6..2.0),
        ];
        scene.push(Prim::Sphere(c, rng.random_range(0.12..0.2)));
    }
    let s = run(&scene);
    let wall = &s.segments[label_at(&s, 2, 2) as usize];
    let clutter: Vec<_> = s.segments.iter().filter(|j| j.centroid[2] < 2.5).collect();
    let pixels: usize = clutter.iter().map(|j| j.size).sum();
    let mean_neg = clutter
        .iter()
        .map(|j| j.neg_entropy * j.size as f64)
        .sum::<f64>()
        / pixels.max(1) as f64;
    println!("clutter: {} segments over {pixels} px, size-weighted neg-entropy {mean_neg:.3}; wall {:.3}", clutter.len(), wall.neg_entropy);
    assert!(clutter.len() >= 3 && pixels > 2000);
    assert!(wall.neg_entropy > 0.95);
    assert!(mean_neg < 0.5, "clutter neg-entropy {mean_neg}");
    assert!(s.mask(0.8).kept_fraction() < 1.0 - pixels as f64 / (W * H) as f64 + 1e-9);
}

/// A large box (a table) with a smaller box on its top face, seen from the front and above;
/// the small box meets the table top at a concave edge.
fn two_boxes() -> Vec<Prim> {
    // Camera y points down: the table top is at y = 0.6 (below the optical axis).
    vec![
        Prim::Plane([0.0, 0.0, -1.0], -4.0),
        Prim::Box([-0.8, 0.6, 1.2], [0.8, 1.5, 3.0]),
        Prim::Box([-0.25, 0.25, 2.0], [0.25, 0.6, 2.5]),
    ]
}

#[test]
fn two_boxes_touching_at_a_concave_edge_split() {
    let cam = camera();
    // Pixels on the small box's front face and on the table top between it and the camera.
    let front = cam.project(glam::DVec3::new(0.0, 0.45, 2.0)).unwrap();
    let top = cam.project(glam::DVec3::new(0.0, 0.6, 1.6)).unwrap();
    let s = run(&two_boxes());
    let lf = label_at(&s, front.x.round() as usize, front.y.round() as usize);
    let lt = label_at(&s, top.x.round() as usize, top.y.round() as usize);
    assert!(lf != NO_SEGMENT && lt != NO_SEGMENT);
    assert_ne!(
        lf, lt,
        "small box front face and table top must be different superjuts"
    );
    // Both faces are planar: near-zero entropy.
    for l in [lf, lt] {
        assert!(
            s.segments[l as usize].neg_entropy > 0.9,
            "{:?}",
            s.segments[l as usize]
        );
    }
    // The table top is horizontal, the front face vertical.
    assert!(
        s.segments[lt as usize].horizontality > 0.95,
        "{}",
        s.segments[lt as usize].horizontality
    );
    assert!(
        s.segments[lf as usize].horizontality < 0.1,
        "{}",
        s.segments[lf as usize].horizontality
    );
}

#[test]
fn segmentation_is_deterministic_across_thread_counts() {
    let rho = render(&two_boxes(), 0.003, 11);
    let cfg = SegmentConfig::default();
    let one = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap();
    let three = rayon::ThreadPoolBuilder::new()
        .num_threads(3)
        .build()
        .unwrap();
    let a = one.install(|| segment::segment_keyframe(&textured(), &rho, &camera(), &cfg).unwrap());
    let b =
        three.install(|| segment::segment_keyframe(&textured(), &rho, &camera(), &cfg).unwrap());
    let c = segment::segment_keyframe(&textured(), &rho, &camera(), &cfg).unwrap();
    assert!(a.segments.len() > 2);
    assert_eq!(a.labels, b.labels);
    assert_eq!(a.labels, c.labels);
    // Features too, to the bit: the sums run in pixel order whatever the thread count.
    assert_eq!(a.segments, b.segments);
    assert_eq!(a.segments, c.segments);
}

/// A `Segmenter` keeps its per-pixel buffers for the next keyframe: nothing of one call may
/// reach the next, whatever size or scene came in between, and freeing them changes nothing
/// either.
#[test]
fn kept_buffers_carry_nothing_between_keyframes() {
    let cfg = SegmentConfig::default();
    let rho = render(&two_boxes(), 0.003, 11);
    let mut segmenter = Segmenter::new();
    assert_eq!(segmenter.scratch_bytes(), 0);
    let first = segmenter
        .segment_keyframe(&textured(), &rho, &camera(), &cfg)
        .unwrap();
    assert!(first.segments.len() > 2);
    // ~130 bytes per pixel kept for the next keyframe.
    let kept = segmenter.scratch_bytes();
    assert!(kept >= 100 * W * H, "{kept} bytes kept");
    // The convenience function (a fresh segmenter) gives the same.
    let alone = segment::segment_keyframe(&textured(), &rho, &camera(), &cfg).unwrap();
    assert_eq!(first.labels, alone.labels);
    assert_eq!(first.segments, alone.segments);
    // A smaller keyframe (resizes every kept buffer), then another scene at the first size.
    let (w2, h2) = (W / 2 + 3, H / 2 - 1);
    let small_cam = PinholeCamera::new(65.0, 65.0, 40.0, 29.0, w2 as u32, h2 as u32);
    let small_rho = ImageF32::filled(w2, h2, 0.4);
    let small_int = ImageF32::filled(w2, h2, 90.0);
    let small = segmenter
        .segment_keyframe(&small_int, &small_rho, &small_cam, &cfg)
        .unwrap();
    assert_eq!(small.labels.len(), w2 * h2);
    let other = segmenter
        .segment_keyframe(
            &textured(),
            &render(&[tilted_plane()], 0.0, 1),
            &camera(),
            &cfg,
        )
        .unwrap();
    assert_eq!(other.segments.len(), 1);
    let again = segmenter
        .segment_keyframe(&textured(), &rho, &camera(), &cfg)
        .unwrap();
    assert_eq!(first.labels, again.labels);
    assert_eq!(first.segments, again.segments);
    assert_eq!(first.normals, again.normals);
    segmenter.release();
    assert_eq!(segmenter.scratch_bytes(), 0);
    let fresh = segmenter
        .segment_keyframe(&textured(), &rho, &camera(), &cfg)
        .unwrap();
    assert_eq!(first.labels, fresh.labels);
    assert_eq!(first.segments, fresh.segments);
    assert!(segmenter.scratch_bytes() >= 100 * W * H);
}

/// Two segmenters used from two threads at the same time give what one gives keyframe after
/// keyframe: each owns its buffers, so neither sees (or frees) the other's.
#[test]
fn segmenters_on_two_threads_match_one_after_the_other() {
    let cfg = SegmentConfig::default();
    let scenes: Vec<ImageF32> = vec![
        render(&two_boxes(), 0.003, 11),
        render(&[tilted_plane()], 0.0, 1),
        render(&two_boxes(), 0.004, 12),
        render(&two_boxes(), 0.002, 13),
    ];
    let mut one = Segmenter::new();
    let sequential: Vec<Superjuts> = scenes
        .iter()
        .chain(scenes.iter().rev())
        .map(|rho| {
            one.segment_keyframe(&textured(), rho, &camera(), &cfg)
                .unwrap()
        })
        .collect();
    let n = scenes.len();
    // Each thread runs the scenes several times, in opposite orders, so their calls overlap
    // and each segmenter's buffers hold another scene than the one it segments next.
    let rounds = 3;
    let run = |order: Vec<usize>| {
        let (scenes, cfg) = (&scenes, &cfg);
        move || {
            let mut segmenter = Segmenter::new();
            let mut out = Vec::new();
            for _ in 0..rounds {
                for &i in &order {
                    let juts = segmenter
                        .segment_keyframe(&textured(), &scenes[i], &camera(), cfg)
                        .unwrap();
                    out.push((i, juts));
                }
            }
            out
        }
    };
    let (a, b) = std::thread::scope(|s| {
        let a = s.spawn(run((0..n).collect()));
        let b = s.spawn(run((0..n).rev().collect()));
        (a.join().unwrap(), b.join().unwrap())
    });
    assert_eq!(a.len(), rounds * n);
    assert_eq!(b.len(), rounds * n);
    for (i, juts) in a.iter().chain(&b) {
        let want = &sequential[*i];
        assert_eq!(juts.labels, want.labels, "scene {i}");
        assert_eq!(juts.segments, want.segments, "scene {i}");
        assert_eq!(juts.normals, want.normals, "scene {i}");
    }
    // The reversed half of the sequential run matches its first half.
    for i in 0..n {
        assert_eq!(sequential[i].labels, sequential[2 * n - 1 - i].labels);
        assert_eq!(sequential[i].segments, sequential[2 * n - 1 - i].segments);
    }
}

#[test]
fn golden_spiral_bins_have_near_equal_areas() {
    let bins = SphereBins::golden(80);
    let mut rng = rand_pcg::Pcg64::seed_from_u64(5);
    let n = 400_000;
    let mut counts = vec![0usize; 80];
    for _ in 0..n {
        // Uniform on the sphere: z uniform in [-1, 1], azimuth uniform.
        let z: f64 = rng.random_range(-1.0..1.0);
        let phi: f64 = rng.random_range(0.0..std::f64::consts::TAU);
        let r = (1.0 - z * z).sqrt();
        counts[bins.bin([(r * phi.cos()) as f32, (r * phi.sin()) as f32, z as f32])] += 1;
    }
    let mean = n as f64 / 80.0;
    let dev: Vec<f64> = counts.iter().map(|&c| c as f64 / mean - 1.0).collect();
    let max_dev = dev.iter().fold(0.0f64, |m, d| m.max(d.abs()));
    let rms = (dev.iter().map(|d| d * d).sum::<f64>() / 80.0).sqrt();
    println!("golden-spiral cell areas: max |rel. dev| {max_dev:.3}, rms {rms:.3}");
    // Monte-Carlo noise alone is ~1/sqrt(5000) = 0.014 rms.
    assert!(max_dev < 0.15, "max deviation {max_dev}");
    assert!(rms < 0.06, "rms deviation {rms}");
}

#[test]
fn mesh_normals_and_segmentation_match_the_image_path() {
    let rho = render(&two_boxes(), 0.0, 1);
    let cam = camera();
    let m = segment::triangulate_depth(&rho, &cam, 0.05);
    assert!(m.triangles.len() > W * H);
    // Vertex normals on the table top point up (-y in the camera frame).
    let top = cam.project(glam::DVec3::new(0.0, 0.6, 1.6)).unwrap();
    let ti = top.y.round() as usize * W + top.x.round() as usize;
    let v = m
        .pixel_of_vertex
        .iter()
        .position(|&p| p as usize == ti)
        .unwrap();
    assert!(m.normals[v][1] < -0.999, "{:?}", m.normals[v]);
    let (labels, segs) = segment::segment_mesh(&m, &SegmentConfig::default()).unwrap();
    let front = cam.project(glam::DVec3::new(0.0, 0.45, 2.0)).unwrap();
    let fi = front.y.round() as usize * W + front.x.round() as usize;
    let vf = m
        .pixel_of_vertex
        .iter()
        .position(|&p| p as usize == fi)
        .unwrap();
    assert_ne!(labels[v], labels[vf]);
    assert!(segs[labels[v] as usize].neg_entropy > 0.9);
    // Projecting the labelled mesh back into the image reproduces the vertex labels.
    let img = segment::project_labels(&m, &labels, &cam, &rgbid::geometry::Se3::default());
    let (mut agree, mut total) = (0, 0);
    for (vi, &p) in m.pixel_of_vertex.iter().enumerate() {
        if img[p as usize] != NO_SEGMENT {
            total += 1;
            agree += usize::from(img[p as usize] == labels[vi]);
        }
    }
    assert!(total as f64 > 0.95 * m.vertices.len() as f64, "{total}");
    assert!(agree as f64 > 0.97 * total as f64, "{agree}/{total}");
}

#[test]
fn point_cloud_triangulation_with_spade_segments_a_sphere_on_a_wall() {
    let rho = render(
        &[
            Prim::Plane([0.0, 0.0, -1.0], -3.0),
            Prim::Sphere([0.0, 0.0, 1.5], 0.4),
        ],
        0.0,
        1,
    );
    // Subsample the points irregularly, as a point cloud would be.
    let pts: Vec<[f32; 3]> = segment::points_from_inverse_depth(&rho, &camera())
        .into_iter()
        .enumerate()
        .filter(|(i, p)| p[2] > 0.0 && (i * 7919) % 3 == 0)
        .map(|(_, p)| p)
        .collect();
    let m = segment::triangulate_points(&pts, 0.1).unwrap();
    assert!(m.triangles.len() > pts.len());
    let cfg = SegmentConfig {
        min_size: 50,
        ..Default::default()
    };
    let (labels, segs) = segment::segment_mesh(&m, &cfg).unwrap();
    // The vertex nearest the image centre is on the sphere; a corner vertex on the wall.
    let centre = (0..pts.len())
        .min_by(|&a, &b| {
            let f = |p: [f32; 3]| (p[0] / p[2]).powi(2) + (p[1] / p[2]).powi(2);
            f(pts[a]).total_cmp(&f(pts[b]))
        })
        .unwrap();
    let corner = (0..pts.len())
        .max_by(|&a, &b| (pts[a][0] + pts[a][1]).total_cmp(&(pts[b][0] + pts[b][1])))
        .unwrap();
    let (s, w) = (
        &segs[labels[centre] as usize],
        &segs[labels[corner] as usize],
    );
    println!(
        "spade mesh: sphere neg {:.3}, wall neg {:.3}, {} segments",
        s.neg_entropy,
        w.neg_entropy,
        segs.len()
    );
    assert_ne!(labels[centre], labels[corner]);
    assert!(s.neg_entropy < 0.5 && w.neg_entropy > 0.9);
}
