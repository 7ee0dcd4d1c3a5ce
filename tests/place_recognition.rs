//! Vocabulary (training, binary round trip, DBoW2 text), keyframe database, Horn and RANSAC.

use glam::{DQuat, DVec3};
use rand::{Rng, SeedableRng};
use rgbid::camera::PinholeCamera;
use rgbid::geometry::Se3;
use rgbid::image::ImageF32;
use rgbid::place::{
    extract_orb, horn_absolute_orientation, ransac_rigid, Descriptor, KeyframeDatabase,
    LoopDetector, LoopDetectorParams, OrbParams, PlaceError, QueryParams, RansacParams,
    TrainParams, Vocabulary,
};

fn random_desc(rng: &mut rand_pcg::Pcg64) -> Descriptor {
    Descriptor([rng.random(), rng.random(), rng.random(), rng.random()])
}

fn perturb(d: &Descriptor, bits: usize, rng: &mut rand_pcg::Pcg64) -> Descriptor {
    let mut d = *d;
    for _ in 0..bits {
        let b = rng.random_range(0..256);
        d.0[b / 64] ^= 1 << (b % 64);
    }
    d
}

/// "Places", each a set of 150 landmark descriptors drawn from a shared pool of appearance
/// prototypes; a view of a place is a random 70 % subset of its landmarks with bit noise.
struct World {
    places: Vec<Vec<Descriptor>>,
}

impl World {
    fn new(n_places: usize, rng: &mut rand_pcg::Pcg64) -> Self {
        let prototypes: Vec<Descriptor> = (0..400).map(|_| random_desc(rng)).collect();
        let places = (0..n_places)
            .map(|_| {
                (0..150)
                    .map(|_| perturb(&prototypes[rng.random_range(0..400)], 30, rng))
                    .collect()
            })
            .collect();
        Self { places }
    }

    fn view(&self, place: usize, rng: &mut rand_pcg::Pcg64) -> Vec<Descriptor> {
        let mut out = Vec::new();
        for d in &self.places[place] {
            if rng.random_bool(0.7) {
                out.push(perturb(d, 6, rng));
            }
        }
        out
    }
}

fn train_small(seed: u64) -> (World, Vocabulary, rand_pcg::Pcg64) {
    let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
    let world = World::new(30, &mut rng);
    let training: Vec<Vec<Descriptor>> = (0..30).map(|p| world.view(p, &mut rng)).collect();
    let voc = Vocabulary::train(
        &training,
        &TrainParams {
            k: 6,
            levels: 3,
            ..Default::default()
        },
    )
    .unwrap();
    (world, voc, rng)
}

#[test]
fn vocabulary_train_save_load_round_trip() {
    let (world, voc, mut rng) = train_small(1);
    assert!(voc.num_words() > 50, "{} words", voc.num_words());
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("v.rgbvoc");
    voc.save(&path).unwrap();
    let loaded = Vocabulary::load(&path).unwrap();
    assert_eq!(loaded, voc);
    let v = world.view(4, &mut rng);
    assert_eq!(loaded.transform(&v, 1), voc.transform(&v, 1));
    // DBoW2 text round trip, through `load`'s format sniffing.
    let tpath = dir.path().join("v.txt");
    let mut buf = Vec::new();
    voc.write_dbow2_text(&mut buf).unwrap();
    std::fs::write(&tpath, &buf).unwrap();
    assert_eq!(Vocabulary::load(&tpath).unwrap(), voc);
    // Truncation and corruption are errors, not panics.
    let bytes = std::fs::read(&path).unwrap();
    for cut in [0, 7, 12, 27, bytes.len() - 1] {
        assert!(
            Vocabulary::read_binary(&bytes[..cut]).is_err(),
            "cut at {cut} accepted"
        );
    }
    let mut bad = bytes.clone();
    bad[28..32].copy_from_slice(&5000u32.to_le_bytes()); // first node's parent
    assert!(matches!(
        Vocabulary::read_binary(&bad),
        Err(PlaceError::BadBinaryVocabulary(_))
    ));
}

#[test]
fn dbow2_text_parses_a_hand_made_file() {
    // k = 2, L = 2, L1 scoring, TF-IDF: root -> {1, 2}; 1 -> {3, 4}; 2 is a leaf.
    let zeros = vec!["0"; 32].join(" ");
    let ones = vec!["255"; 32].join(" ");
    let mut quarter = vec!["0"; 32];
    quarter[..8].iter_mut().for_each(|s| *s = "255");
    let quarter = quarter.join(" ");
    let text =
        format!("2 2 0 0\n0 0 {zeros} 0\n0 1 {ones} 0.5\n1 1 {zeros} 1.25\n1 1 {quarter} 2\n");
    let voc = Vocabulary::read_dbow2_text(text.as_bytes()).unwrap();
    assert_eq!(
        (voc.k(), voc.levels(), voc.num_nodes(), voc.num_words()),
        (2, 2, 5, 3)
    );
    // Words in node order: node 2 -> word 0, node 3 -> word 1, node 4 -> word 2.
    assert_eq!(voc.word_weight(0), Some(0.5));
    assert_eq!(voc.word_weight(1), Some(1.25));
    assert_eq!(voc.word_weight(2), Some(2.0));
    assert_eq!(voc.word_of(&Descriptor([u64::MAX; 4])), 0);
    assert_eq!(voc.word_of(&Descriptor([0; 4])), 1);
    assert_eq!(voc.word_of(&Descriptor([u64::MAX, 0, 0, 0])), 2);
    // BoW: TF-IDF, L1-normalised. Two features on word 1 (w 1.25), one on word 2 (w 2).
    let (bow, fv) = voc.transform(
        &[
            Descriptor([0; 4]),
            Descriptor([0; 4]),
            Descriptor([u64::MAX, 0, 0, 0]),
        ],
        1,
    );
    let total = 2.0 * 1.25 + 2.0;
    assert_eq!(bow.0.len(), 2);
    assert!((bow.0[0].1 - 2.5 / total).abs() < 1e-12 && (bow.0[1].1 - 2.0 / total).abs() < 1e-12);
    assert_eq!(
        fv.get(&1).map(Vec::len),
        Some(3),
        "all three features pass through node 1"
    );

    // Malformed files.
    let cases = [
        ("", "empty"),
        ("2 2 0\n", "short header"),
        ("x 2 0 0\n0 1 {zeros} 1\n", "non-numeric k"),
        ("2 2 9 0\n", "scoring out of range"),
        ("2 2 0 0\n0 1 1 2 3 1\n", "short node line"),
        ("2 2 0 0\n5 1 {zeros} 1\n", "parent does not precede"),
        ("2 2 0 0\n0 1 {zeros} 1\n1 1 {zeros} 1\n", "leaf as parent"),
        ("2 2 0 0\n0 0 {zeros} 1\n", "inner node without children"),
        ("2 2 0 0\n0 1 {big} 1\n", "byte out of range"),
        ("2 2 0 0\n0 1 {zeros} abc\n", "bad weight"),
        ("2 2 3 0\n0 1 {zeros} 1\n", "unsupported scoring"),
    ];
    let big = vec!["256"; 32].join(" ");
    for (c, what) in cases {
        let t = c.replace("{zeros}", &zeros).replace("{big}", &big);
        assert!(
            Vocabulary::read_dbow2_text(t.as_bytes()).is_err(),
            "{what} accepted"
        );
    }
}

#[test]
fn database_returns_the_revisited_keyframe() {
    let (world, voc, mut rng) = train_small(2);
    let mut db = KeyframeDatabase::new(voc.num_words(), voc.scoring());
    // A trajectory through places 0..20 (two keyframes per place), then revisits of 3, 11, 17.
    let mut kf_place = Vec::new();
    for p in 0..20 {
        for _ in 0..2 {
            let id = kf_place.len();
            let (bow, _) = voc.transform(&world.view(p, &mut rng), 1);
            db.add(id, vec![bow]).unwrap();
            kf_place.push(p);
        }
    }
    let params = QueryParams {
        max_results: 3,
        min_separation: 4,
        min_normalised_score: 0.3,
        min_reference_score: 0.0,
    };
    for revisit in [3usize, 11, 17] {
        let id = kf_place.len();
        let bow = voc.transform(&world.view(revisit, &mut rng), 1).0;
        let reference = db
            .score_against(std::slice::from_ref(&bow), id - 1)
            .unwrap();
        let c = db.query(id, std::slice::from_ref(&bow), reference, &params);
        assert!(!c.is_empty(), "no candidate for place {revisit}");
        assert_eq!(
            kf_place[c[0].keyframe_id], revisit,
            "best candidate {:?}",
            c[0]
        );
        // Both keyframes of the revisited place outrank every other place by a margin.
        let other = c
            .iter()
            .find(|x| kf_place[x.keyframe_id] != revisit)
            .map_or(0.0, |x| x.score);
        assert!(
            c.len() >= 2 && kf_place[c[1].keyframe_id] == revisit,
            "{c:?}"
        );
        assert!(c[0].score > 1.3 * other, "{c:?}");
        // The brute-force score agrees with the inverted-index score.
        let direct = db
            .score_against(std::slice::from_ref(&bow), c[0].keyframe_id)
            .unwrap();
        assert!((direct - c[0].score).abs() < 1e-12);
        db.add(id, vec![bow]).unwrap();
        kf_place.push(revisit);
    }
    // Temporal separation: a query right after a keyframe of the same place does not return it.
    let id = kf_place.len();
    let bow = voc.transform(&world.view(17, &mut rng), 1).0;
    let c = db.query(
        id,
        std::slice::from_ref(&bow),
        0.1,
        &QueryParams {
            min_separation: 100,
            ..params
        },
    );
    assert!(c.is_empty());
    // Several histograms per keyframe: the best one counts.
    let mut db2 = KeyframeDatabase::new(voc.num_words(), voc.scoring());
    let a = voc.transform(&world.view(5, &mut rng), 1).0;
    let b = voc.transform(&world.view(9, &mut rng), 1).0;
    db2.add(0, vec![a, b]).unwrap();
    let q = voc.transform(&world.view(9, &mut rng), 1).0;
    let s = db2.query(
        50,
        std::slice::from_ref(&q),
        1.0,
        &QueryParams {
            min_normalised_score: 0.0,
            ..params
        },
    );
    let sb = db2.score_against(std::slice::from_ref(&q), 0).unwrap();
    assert_eq!(s.len(), 1);
    assert!((s[0].score - sb).abs() < 1e-12 && sb > 0.2);
}

fn random_transform(rng: &mut rand_pcg::Pcg64) -> Se3 {
    let axis = DVec3::new(
        rng.random_range(-1.0..1.0),
        rng.random_range(-1.0..1.0),
        rng.random_range(-1.0..1.0),
    )
    .normalize();
    let q = DQuat::from_axis_angle(axis, rng.random_range(-2.5..2.5));
    Se3::new(
        q,
        DVec3::new(
            rng.random_range(-2.0..2.0),
            rng.random_range(-2.0..2.0),
            rng.random_range(-2.0..2.0),
        ),
    )
}

fn pose_error(a: &Se3, b: &Se3) -> (f64, f64) {
    let d = a.inverse() * *b;
    (d.translation.length(), d.angle())
}

#[test]
fn horn_recovers_exact_transforms() {
    let mut rng = rand_pcg::Pcg64::seed_from_u64(4);
    for n in [3usize, 4, 10, 200] {
        for _ in 0..20 {
            let a_from_b = random_transform(&mut rng);
            let b: Vec<DVec3> = (0..n)
                .map(|_| {
                    DVec3::new(
                        rng.random_range(-1.0..1.0),
                        rng.random_range(-1.0..1.0),
                        rng.random_range(0.5..4.0),
                    )
                })
                .collect();
            let a: Vec<DVec3> = b.iter().map(|p| a_from_b.transform_point(*p)).collect();
            let est = horn_absolute_orientation(&a, &b).unwrap();
            let (dt, dr) = pose_error(&est, &a_from_b);
            assert!(dt < 1e-9 && dr < 1e-9, "n={n}: {dt} m, {dr} rad");
        }
    }
    // Degenerate input is an error, not a wrong answer.
    let line: Vec<DVec3> = (0..5).map(|i| DVec3::new(i as f64, 0.0, 1.0)).collect();
    assert!(matches!(
        horn_absolute_orientation(&line, &line),
        Err(PlaceError::Degenerate(_))
    ));
    assert!(horn_absolute_orientation(&line[..2], &line[..2]).is_err());
    assert!(horn_absolute_orientation(&line[..4], &line[..3]).is_err());
}

#[test]
fn ransac_with_half_outliers_finds_the_inliers() {
    let mut rng = rand_pcg::Pcg64::seed_from_u64(5);
    for trial in 0..5 {
        let a_from_b = random_transform(&mut rng);
        let n = 120;
        let mut a = Vec::new();
        let mut b = Vec::new();
        let mut truth = Vec::new();
        for i in 0..n {
            let pb = DVec3::new(
                rng.random_range(-2.0..2.0),
                rng.random_range(-1.5..1.5),
                rng.random_range(0.8..5.0),
            );
            let noise = DVec3::new(
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
            ) * 0.003;
            b.push(pb);
            if i % 2 == 0 {
                a.push(a_from_b.transform_point(pb) + noise);
                truth.push(i);
            } else {
                // Outlier: a random point in the same volume.
                a.push(a_from_b.transform_point(DVec3::new(
                    rng.random_range(-2.0..2.0),
                    rng.random_range(-1.5..1.5),
                    rng.random_range(0.8..5.0),
                )));
            }
        }
        let r = ransac_rigid(
            &a,
            &b,
            &RansacParams {
                threshold: 0.02,
                seed: trial,
                ..Default::default()
            },
        )
        .unwrap();
        let (dt, dr) = pose_error(&r.a_from_b, &a_from_b);
        assert!(
            dt < 0.01 && dr < 0.5f64.to_radians(),
            "trial {trial}: {dt} m, {} deg",
            dr.to_degrees()
        );
        let found: std::collections::BTreeSet<usize> = r.inliers.iter().copied().collect();
        let missed = truth.iter().filter(|i| !found.contains(i)).count();
        let wrong = found.iter().filter(|i| *i % 2 == 1).count();
        assert!(
            missed == 0 && wrong <= 1,
            "trial {trial}: missed {missed}, wrong {wrong}"
        );
    }
}

/// A textured plane `z = 2 m` (world frame) seen by a pinhole camera: exact intensity and
/// inverse depth by ray casting.
struct PlaneWorld {
    texture: Vec<f32>,
    size: usize,
}

impl PlaneWorld {
    fn new(seed: u64) -> Self {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
        let size = 1024;
        let mut texture = vec![0.0f32; size * size];
        for (i, t) in texture.iter_mut().enumerate() {
            *t = 80.0 + 60.0 * (i % size) as f32 / size as f32;
        }
        for _ in 0..900 {
            let (x0, y0) = (rng.random_range(0..size), rng.random_range(0..size));
            let (rw, rh) = (rng.random_range(4..40), rng.random_range(4..40));
            let v: f32 = rng.random_range(0.0..255.0);
            let disc = rng.random_bool(0.4);
            for y in y0..(y0 + rh).min(size) {
                for x in x0..(x0 + rw).min(size) {
                    let (dx, dy) = (
                        x as f64 - (x0 + rw / 2) as f64,
                        y as f64 - (y0 + rh / 2) as f64,
                    );
                    if !disc || dx * dx + dy * dy < (rw.min(rh) as f64 / 2.0).powi(2) {
                        texture[y * size + x] = v;
                    }
                }
            }
        }
        Self { texture, size }
    }

    fn sample(&self, x: f64, y: f64) -> f32 {
        // World [-2, 2] m -> texels.
        let fx = ((x + 2.0) / 4.0 * self.size as f64).clamp(0.0, (self.size - 2) as f64);
        let fy = ((y + 2.0) / 4.0 * self.size as f64).clamp(0.0, (self.size - 2) as f64);
        let (ix, iy) = (fx as usize, fy as usize);
        let (tx, ty) = ((fx - ix as f64) as f32, (fy - iy as f64) as f32);
        let t = |x: usize, y: usize| self.texture[y * self.size + x];
        let a = t(ix, iy) + (t(ix + 1, iy) - t(ix, iy)) * tx;
        let b = t(ix, iy + 1) + (t(ix + 1, iy + 1) - t(ix, iy + 1)) * tx;
        a + (b - a) * ty
    }

    fn render(&self, camera: &PinholeCamera, world_from_camera: &Se3) -> (ImageF32, ImageF32) {
        let (w, h) = (camera.width as usize, camera.height as usize);
        let mut img = ImageF32::filled(w, h, 0.0);
        let mut inv = ImageF32::filled(w, h, 0.0);
        for v in 0..h {
            for u in 0..w {
                let ray_c = DVec3::new(
                    (u as f64 - camera.cx) / camera.fx,
                    (v as f64 - camera.cy) / camera.fy,
                    1.0,
                );
                let ray = world_from_camera.rotation * ray_c;
                let o = world_from_camera.translation;
                let t = (2.0 - o.z) / ray.z;
                let p = o + ray * t;
                img.data_mut()[v * w + u] = self.sample(p.x, p.y);
                inv.data_mut()[v * w + u] = (1.0 / t) as f32;
            }
        }
        (img, inv)
    }
}

#[test]
fn loop_detector_closes_a_synthetic_loop_with_the_right_relative_pose() {
    let camera = PinholeCamera::new(250.0, 250.0, 159.5, 119.5, 320, 240);
    let orb = OrbParams {
        n_features: 500,
        ..Default::default()
    };
    // Vocabulary from views of a different texture.
    let other = PlaneWorld::new(11);
    let training: Vec<Vec<Descriptor>> = (0..8)
        .map(|i| {
            let pose = Se3::new(
                DQuat::IDENTITY,
                DVec3::new(-1.0 + 0.25 * i as f64, 0.3 * (i % 3) as f64 - 0.3, 0.0),
            );
            extract_orb(&other.render(&camera, &pose).0, None, &orb)
                .unwrap()
                .descriptors
        })
        .collect();
    let voc = Vocabulary::train(
        &training,
        &TrainParams {
            k: 8,
            levels: 3,
            ..Default::default()
        },
    )
    .unwrap();
    let world = PlaneWorld::new(12);
    let mut params = LoopDetectorParams {
        orb,
        direct_index_depth: 1,
        ..Default::default()
    };
    params.query.min_separation = 8;
    let mut det = LoopDetector::new(voc, params);
    // Out along x by 1.2 m, then back along a parallel line 5 cm lower with a small yaw.
    let mut poses = Vec::new();
    for i in 0..12 {
        poses.push(Se3::new(
            DQuat::IDENTITY,
            DVec3::new(0.1 * i as f64, 0.0, 0.0),
        ));
    }
    for i in 0..12 {
        let yaw =
            DQuat::from_rotation_y(3f64.to_radians()) * DQuat::from_rotation_z(5f64.to_radians());
        poses.push(Se3::new(yaw, DVec3::new(1.15 - 0.1 * i as f64, 0.05, 0.1)));
    }
    let mut loops = Vec::new();
    for p in &poses {
        let (img, inv) = world.render(&camera, p);
        let desc = det.describe(&img, &inv, &camera, &[]).unwrap();
        if let (_, Some(l)) = det.insert(desc).unwrap() {
            loops.push(l);
        }
    }
    assert!(
        loops.iter().filter(|l| l.query_id >= 12).count() >= 3,
        "loops: {:?}",
        loops
            .iter()
            .map(|l| (l.query_id, l.candidate_id))
            .collect::<Vec<_>>()
    );
    for l in &loops {
        assert!(l.candidate_id + 8 <= l.query_id);
        let truth = poses[l.query_id].inverse() * poses[l.candidate_id];
        let (dt, dr) = pose_error(&l.loop_match.query_from_candidate, &truth);
        assert!(
            dt < 0.02 && dr < 1f64.to_radians(),
            "loop {}->{}: {dt} m, {dr} rad",
            l.query_id,
            l.candidate_id
        );
        assert!(l.loop_match.inliers.len() >= 10 && l.loop_match.hull_fraction >= 0.05);
    }
}
