//! ORB invariances and descriptor matching on synthetic images rendered analytically, so a
//! rotated / scaled view is exact (no resampling of a raster).

use glam::DVec2;
use rand::{Rng, SeedableRng};
use rgbid::image::ImageF32;
use rgbid::place::{extract_orb, hamming, match_descriptors, Descriptor, MatchParams, OrbParams};

/// A piecewise-constant scene of random rectangles and discs over a gradient, in continuous
/// scene coordinates `[0, 1]^2`.
struct Scene {
    rects: Vec<(DVec2, DVec2, f64, f32)>,
    discs: Vec<(DVec2, f64, f32)>,
}

impl Scene {
    fn random(seed: u64) -> Self {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
        let rects = (0..90)
            .map(|_| {
                let c = DVec2::new(rng.random_range(0.0..1.0), rng.random_range(0.0..1.0));
                let h = DVec2::new(rng.random_range(0.01..0.07), rng.random_range(0.01..0.07));
                (
                    c,
                    h,
                    rng.random_range(0.0..1.5),
                    rng.random_range(0.0..255.0),
                )
            })
            .collect();
        let discs = (0..40)
            .map(|_| {
                let c = DVec2::new(rng.random_range(0.0..1.0), rng.random_range(0.0..1.0));
                (
                    c,
                    rng.random_range(0.01..0.04),
                    rng.random_range(0.0..255.0),
                )
            })
            .collect();
        Self { rects, discs }
    }

    fn value(&self, p: DVec2) -> f32 {
        let mut v = (60.0 + 80.0 * p.x + 40.0 * p.y) as f32;
        for (c, h, a, val) in &self.rects {
            let d = DVec2::from_angle(-*a).rotate(p - *c);
            if d.x.abs() < h.x && d.y.abs() < h.y {
                v = *val;
            }
        }
        for (c, r, val) in &self.discs {
            if (p - *c).length() < *r {
                v = *val;
            }
        }
        v
    }
}

/// Renders `w x h` pixels where pixel `q` shows scene point `scene_from_pixel(q)`, 3x3
/// supersampled.
fn render(
    scene: &Scene,
    w: usize,
    h: usize,
    scene_from_pixel: impl Fn(DVec2) -> DVec2,
) -> ImageF32 {
    let mut img = ImageF32::filled(w, h, 0.0);
    for y in 0..h {
        for x in 0..w {
            let mut acc = 0.0;
            for sy in 0..3 {
                for sx in 0..3 {
                    let q = DVec2::new(
                        x as f64 + (sx as f64 - 1.0) / 3.0,
                        y as f64 + (sy as f64 - 1.0) / 3.0,
                    );
                    acc += scene.value(scene_from_pixel(q));
                }
            }
            img.data_mut()[y * w + x] = acc / 9.0;
        }
    }
    img
}

/// Fraction of mutual matches whose keypoints agree with the true pixel mapping within
/// `tol` pixels, and their number.
fn check_view(angle: f64, scale: f64) -> (usize, f64, f64) {
    let scene = Scene::random(3);
    let (w, h) = (320usize, 240usize);
    let size = 300.0; // scene units -> pixels in the reference view
    let centre = DVec2::new(w as f64 / 2.0, h as f64 / 2.0);
    let reference = render(&scene, w, h, |q| (q - centre) / size + DVec2::splat(0.5));
    // Second view: pixel q shows the reference pixel r = centre + R^-1 (q - centre) / scale.
    let inv = DVec2::from_angle(-angle);
    let ref_from_view = move |q: DVec2| centre + inv.rotate(q - centre) / scale;
    let view = render(&scene, w, h, |q| {
        (ref_from_view(q) - centre) / size + DVec2::splat(0.5)
    });
    let params = OrbParams {
        n_features: 500,
        ..Default::default()
    };
    let fa = extract_orb(&reference, None, &params).unwrap();
    let fb = extract_orb(&view, None, &params).unwrap();
    assert!(
        fa.len() > 300 && fb.len() > 300,
        "found {} and {} keypoints",
        fa.len(),
        fb.len()
    );
    let m = match_descriptors(
        &fa.descriptors,
        &fb.descriptors,
        &MatchParams {
            max_distance: 64,
            ratio: 0.8,
            mutual: true,
        },
    );
    let mut good = 0;
    let mut angle_err = Vec::new();
    for mm in &m {
        let pa = fa.keypoints[mm.query].uv;
        let pb_in_ref = ref_from_view(fb.keypoints[mm.train].uv);
        if (pa - pb_in_ref).length() < 3.0 * scale.max(1.0 / scale) {
            good += 1;
            let mut d =
                f64::from(fb.keypoints[mm.train].angle - fa.keypoints[mm.query].angle) - angle;
            d = (d + std::f64::consts::PI).rem_euclid(2.0 * std::f64::consts::PI)
                - std::f64::consts::PI;
            angle_err.push(d.abs());
        }
    }
    angle_err.sort_by(f64::total_cmp);
    let median_angle = angle_err
        .get(angle_err.len() / 2)
        .copied()
        .unwrap_or(f64::INFINITY);
    (good, good as f64 / m.len().max(1) as f64, median_angle)
}

#[test]
fn descriptors_of_a_rotated_image_match_the_original() {
    let (good, frac, med_angle) = check_view(35f64.to_radians(), 1.0);
    assert!(good >= 60, "only {good} correct matches");
    assert!(
        frac > 0.8,
        "only {:.0}% of matches are correct",
        100.0 * frac
    );
    assert!(
        med_angle < 5f64.to_radians(),
        "orientation error {:.1} deg",
        med_angle.to_degrees()
    );
}

#[test]
fn descriptors_of_a_scaled_image_match_the_original() {
    let (good, frac, _) = check_view(0.0, 1.4);
    assert!(good >= 40, "only {good} correct matches");
    assert!(
        frac > 0.8,
        "only {:.0}% of matches are correct",
        100.0 * frac
    );
}

#[test]
fn descriptors_of_a_rotated_and_scaled_image_match_the_original() {
    let (good, frac, _) = check_view(-80f64.to_radians(), 0.8);
    assert!(good >= 40, "only {good} correct matches");
    assert!(
        frac > 0.8,
        "only {:.0}% of matches are correct",
        100.0 * frac
    );
}

#[test]
fn keypoints_are_spread_over_the_image_and_respect_the_mask() {
    let scene = Scene::random(5);
    let (w, h) = (320usize, 240usize);
    let img = render(&scene, w, h, |q| q / 300.0);
    let params = OrbParams {
        n_features: 400,
        ..Default::default()
    };
    // The default keeps each level's strongest corners (OpenCV); the grid (ORB-SLAM) spreads
    // them, so every quadrant gets a share.
    let default = extract_orb(&img, None, &params).unwrap();
    assert!(
        default.len() >= 300 && default.len() <= 400,
        "{} keypoints",
        default.len()
    );
    let params = OrbParams {
        distribute: true,
        ..params
    };
    let f = extract_orb(&img, None, &params).unwrap();
    assert!(f.len() >= 300 && f.len() <= 400, "{} keypoints", f.len());
    for (qx, qy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
        let n = f
            .keypoints
            .iter()
            .filter(|k| {
                (k.uv.x >= (w / 2) as f64) == (qx == 1) && (k.uv.y >= (h / 2) as f64) == (qy == 1)
            })
            .count();
        assert!(
            n > f.len() / 8,
            "quadrant ({qx},{qy}) has {n} of {}",
            f.len()
        );
    }
    // Several pyramid levels are used.
    let levels: std::collections::BTreeSet<u8> = f.keypoints.iter().map(|k| k.level).collect();
    assert!(levels.len() >= 5, "levels used: {levels:?}");
    let levels: std::collections::BTreeSet<u8> =
        default.keypoints.iter().map(|k| k.level).collect();
    assert!(levels.len() >= 5, "levels used by default: {levels:?}");
    // Mask: left half only.
    let mut mask = ImageF32::filled(w, h, 0.0);
    for y in 0..h {
        for x in 0..w / 2 {
            mask.data_mut()[y * w + x] = 1.0;
        }
    }
    for distribute in [false, true] {
        let params = OrbParams {
            distribute,
            ..params.clone()
        };
        let fm = extract_orb(&img, Some(&mask), &params).unwrap();
        assert!(fm.len() > 100);
        assert!(
            fm.keypoints.iter().all(|k| k.uv.x.round() < (w / 2) as f64),
            "a keypoint escaped the mask"
        );
    }
}

#[test]
fn hamming_ratio_and_mutual_matching() {
    let mut rng = rand_pcg::Pcg64::seed_from_u64(9);
    let a: Vec<Descriptor> = (0..200)
        .map(|_| Descriptor([rng.random(), rng.random(), rng.random(), rng.random()]))
        .collect();
    // b = a permuted, with 10 flipped bits each, plus 50 random distractors.
    let perm: Vec<usize> = (0..200).rev().collect();
    let mut b: Vec<Descriptor> = perm
        .iter()
        .map(|&i| {
            let mut d = a[i];
            for _ in 0..10 {
                let bit = rng.random_range(0..256);
                d.0[bit / 64] ^= 1 << (bit % 64);
            }
            d
        })
        .collect();
    for _ in 0..50 {
        b.push(Descriptor([
            rng.random(),
            rng.random(),
            rng.random(),
            rng.random(),
        ]));
    }
    assert_eq!(hamming(&a[0], &a[0]), 0);
    assert_eq!(
        hamming(
            &a[0],
            &Descriptor([!a[0].0[0], !a[0].0[1], !a[0].0[2], !a[0].0[3]])
        ),
        256
    );
    let m = match_descriptors(&a, &b, &MatchParams::default());
    assert_eq!(m.len(), 200);
    for mm in &m {
        assert_eq!(perm[mm.train], mm.query);
        assert!(mm.distance <= 10);
    }
    // A query with two equally good train descriptors fails the ratio test.
    let q = vec![a[0]];
    let t = vec![a[0], a[0]];
    assert!(match_descriptors(
        &q,
        &t,
        &MatchParams {
            mutual: false,
            ..Default::default()
        }
    )
    .is_empty());
    assert_eq!(
        match_descriptors(
            &q,
            &t,
            &MatchParams {
                ratio: 1.0,
                mutual: false,
                ..Default::default()
            }
        )
        .len(),
        1
    );
    // Mutual consistency: two queries share one best train descriptor; only the closer survives.
    let mut near = a[1];
    near.0[0] ^= 1;
    let mut far = a[1];
    far.0[0] ^= 0b111;
    let m = match_descriptors(
        &[far, near],
        &[a[1]],
        &MatchParams {
            ratio: 1.0,
            mutual: true,
            max_distance: 64,
        },
    );
    assert_eq!(m.len(), 1);
    assert_eq!(m[0].query, 1);
    let m = match_descriptors(
        &[far, near],
        &[a[1]],
        &MatchParams {
            ratio: 1.0,
            mutual: false,
            max_distance: 64,
        },
    );
    assert_eq!(m.len(), 2);
}
