//! TSDF reconstruction on generated scenes with exact geometry: mesh accuracy and
//! completeness, ray casting, PLY output, input errors.

use std::sync::Arc;

use glam::DVec3;
use rgbid::camera::PinholeCamera;
use rgbid::geometry::Se3;
use rgbid::gpu::ComputeBackend;
use rgbid::image::RgbdFrame;
use rgbid::synth::{
    CameraModel, RenderBackend, Scene, SensorModel, Sequence, SequenceConfig, Trajectory,
    TrajectoryKind,
};
use rgbid::tsdf::{mesh_accuracy, thin_points, TsdfError, TsdfParams, TsdfVolume};

fn camera() -> PinholeCamera {
    PinholeCamera::new(131.25, 131.25, 79.5, 59.5, 160, 120)
}

/// A frame, its `world_from_camera` and its true depth (m, 0 = nothing hit).
type Posed = (RgbdFrame, Se3, Vec<f32>);

/// Frames of the office scene along a handheld path.
fn frames(n: usize) -> (Arc<Scene>, Vec<Posed>) {
    let scene = Arc::new(Scene::preset("office", 1).unwrap());
    let traj = Trajectory::new(TrajectoryKind::Handheld, &scene, 2.0, 1).unwrap();
    // A Kinect's noise (disparity noise at its 525 px focal length) on a small image, so
    // the volume's default inverse-depth sigma describes the frames.
    let mut sensor = SensorModel::kinect();
    sensor.focal_px = Some(525.0);
    let config = SequenceConfig {
        frames: n,
        fps: n as f64 / 2.0,
        seed: 1,
        sensor,
        ..Default::default()
    };
    let seq = Sequence::new(
        scene.clone(),
        CameraModel::Pinhole(camera()),
        traj,
        config,
        &RenderBackend::Cpu,
    )
    .unwrap();
    let out = seq
        .map(|f| {
            let f = f.unwrap();
            (
                f.frame.to_rgbd_frame(f.timestamp),
                f.world_from_camera,
                f.frame.true_depth.data().to_vec(),
            )
        })
        .collect();
    (scene, out)
}

/// True surface points of the pixels with a measurement.
fn seen_surface(cam: &PinholeCamera, data: &[Posed]) -> Vec<DVec3> {
    let mut pts = Vec::new();
    for (frame, pose, truth) in data {
        let w = cam.width as usize;
        for (i, (&rho, &z)) in frame.inverse_depth().data().iter().zip(truth).enumerate() {
            if rho > 0.0 && z > 0.0 {
                let (u, v) = ((i % w) as f64, (i / w) as f64);
                let z = f64::from(z);
                let p = DVec3::new((u - cam.cx) / cam.fx * z, (v - cam.cy) / cam.fy * z, z);
                pts.push(pose.transform_point(p));
            }
        }
    }
    thin_points(&pts, 0.01)
}

fn volume(data: &[Posed], voxel: f64) -> TsdfVolume {
    let params = TsdfParams {
        voxel_size: voxel,
        ..Default::default()
    };
    let mut vol = TsdfVolume::new(params, camera(), &ComputeBackend::Cpu).unwrap();
    for (frame, pose, _) in data {
        vol.integrate(frame, pose).unwrap();
    }
    vol
}

#[test]
fn mesh_of_noisy_frames_lies_on_the_true_surface_and_covers_it() {
    let (scene, data) = frames(12);
    let vol = volume(&data, 0.02);
    assert_eq!(vol.frames(), 12);
    let mesh = vol.extract_mesh().unwrap();
    assert!(
        mesh.triangles.len() > 1000,
        "{} triangles",
        mesh.triangles.len()
    );
    let reference = seen_surface(&camera(), &data);
    let acc = mesh_accuracy(
        &mesh.vertices,
        |p| scene.surface_distance(p),
        &reference,
        0.02,
    );
    eprintln!("{acc:?}");
    assert!(acc.mean_m < 0.006, "{acc:?}");
    assert!(acc.p90_m < 0.014, "{acc:?}");
    assert!(acc.completeness > 0.95, "{acc:?}");
    // The frames have colour: the mesh is not grey.
    assert!(mesh.colours.iter().any(|c| c[0] != c[1] || c[1] != c[2]));
}

#[test]
fn ray_cast_depth_matches_the_true_depth() {
    let (_, data) = frames(12);
    let vol = volume(&data, 0.02);
    let (frame, pose, truth) = &data[6];
    let cast = vol.ray_cast(&camera(), pose).unwrap();
    // Colour: where a surface was found, the ray cast colour is that of the frame seen from
    // the same pose (averaged over the frames and the voxels around the hit), far closer to it
    // than the frame's mean colour is.
    let rgb = frame.colour().expect("generated frames have colour");
    let mut cast_err = Vec::new();
    let mut mean_err = Vec::new();
    let hits: Vec<usize> = (0..truth.len())
        .filter(|&i| cast.depth.data()[i] > 0.0)
        .collect();
    let mean: [f64; 3] = [0, 1, 2].map(|k| {
        hits.iter()
            .map(|&i| f64::from(rgb.rgb()[3 * i + k]))
            .sum::<f64>()
            / hits.len() as f64
    });
    for &i in &hits {
        let seen = [0, 1, 2].map(|k| f64::from(rgb.rgb()[3 * i + k]));
        let c = cast.colours[i].map(f64::from);
        cast_err.push((0..3).map(|k| (c[k] - seen[k]).abs()).sum::<f64>() / 3.0);
        mean_err.push((0..3).map(|k| (mean[k] - seen[k]).abs()).sum::<f64>() / 3.0);
    }
    assert!(cast
        .depth
        .data()
        .iter()
        .zip(&cast.colours)
        .all(|(&d, c)| d > 0.0 || *c == [0; 3]));
    cast_err.sort_by(f64::total_cmp);
    mean_err.sort_by(f64::total_cmp);
    let (cast_med, mean_med) = (cast_err[cast_err.len() / 2], mean_err[mean_err.len() / 2]);
    eprintln!("colour: median error {cast_med:.1} (mean colour: {mean_med:.1}) levels");
    assert!(
        cast_med < 0.5 * mean_med,
        "ray cast colour {cast_med} levels off, the mean colour {mean_med}"
    );
    let mut err: Vec<f64> = Vec::new();
    let mut with_truth = 0usize;
    let mut with_normal = 0usize;
    for (i, &z) in truth.iter().enumerate() {
        if z > 0.5 && z < 4.0 {
            with_truth += 1;
            let d = cast.depth.data()[i];
            if d > 0.0 {
                err.push(f64::from((d - z).abs()));
                let n = cast.normals[i];
                let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
                // A normal needs the voxels one step around the hit observed.
                if len > 0.0 {
                    let c = camera();
                    let ray = [
                        ((i % 160) as f64 - c.cx) / c.fx,
                        ((i / 160) as f64 - c.cy) / c.fy,
                        1.0,
                    ];
                    let facing: f64 = (0..3).map(|k| ray[k] * f64::from(n[k])).sum();
                    assert!((len - 1.0).abs() < 1e-3 && facing < 0.0, "normal {n:?}");
                    with_normal += 1;
                }
            }
        }
    }
    err.sort_by(f64::total_cmp);
    let coverage = err.len() as f64 / with_truth as f64;
    let median = err[err.len() / 2];
    assert!(coverage > 0.85, "ray cast found {coverage} of the surface");
    assert!(median < 0.006, "median depth error {median} m");
    assert!(
        with_normal as f64 > 0.95 * err.len() as f64,
        "{with_normal} normals"
    );
}

#[test]
fn mesh_ply_keeps_the_vertices() {
    let (_, data) = frames(3);
    let vol = volume(&data, 0.04);
    let mesh = vol.extract_mesh().unwrap();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("mesh.ply");
    mesh.write_ply(&path).unwrap();
    let back = rgbid::io::ply::read_ply(&path).unwrap();
    assert_eq!(back.len(), mesh.vertices.len());
    for ((p, c), (v, k)) in back.iter().zip(mesh.vertices.iter().zip(&mesh.colours)) {
        assert_eq!(p.x as f32, v[0]);
        assert_eq!(p.z as f32, v[2]);
        assert_eq!(c, k);
    }
}

#[test]
fn bad_input_is_an_error() {
    let bad = TsdfParams {
        voxel_size: -0.01,
        ..Default::default()
    };
    assert!(matches!(
        TsdfVolume::new(bad, camera(), &ComputeBackend::Cpu),
        Err(TsdfError::InvalidParameter {
            name: "voxel_size",
            ..
        })
    ));
    let mut vol = TsdfVolume::new(TsdfParams::default(), camera(), &ComputeBackend::Cpu).unwrap();
    let small = rgbid::image::test_pattern(80, 60, 1);
    assert!(matches!(
        vol.integrate(&small, &Se3::IDENTITY),
        Err(TsdfError::FrameSize { .. })
    ));
    let frame = rgbid::image::test_pattern(160, 120, 1);
    let nan = Se3 {
        rotation: glam::DQuat::IDENTITY,
        translation: DVec3::new(f64::NAN, 0.0, 0.0),
    };
    assert!(matches!(
        vol.integrate(&frame, &nan),
        Err(TsdfError::NonFinitePose)
    ));
}

/// `rgbid mesh --save-volume` half-way and `rgbid mesh --volume` with the other half of the
/// poses give the same mesh and volume files as one run over every frame; `--volume` alone
/// re-extracts the same mesh; a corrupt volume is an error naming the file.
#[test]
fn cli_mesh_resumes_from_a_saved_volume_exactly() {
    let exe = env!("CARGO_BIN_EXE_rgbid");
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let run = |args: &[&str]| {
        let o = std::process::Command::new(exe)
            .args(args)
            .current_dir(d)
            .output()
            .unwrap();
        (
            o.status.success(),
            format!(
                "{}{}",
                String::from_utf8_lossy(&o.stdout),
                String::from_utf8_lossy(&o.stderr)
            ),
        )
    };
    let ok = |args: &[&str]| {
        let (success, text) = run(args);
        assert!(success, "rgbid {args:?}:\n{text}");
        text
    };
    ok(&[
        "synth", "--frames", "8", "--width", "160", "--seed", "2", "--out", "seq",
    ]);
    let gt = std::fs::read_to_string(d.join("seq/groundtruth.txt")).unwrap();
    let poses: Vec<&str> = gt.lines().filter(|l| !l.starts_with('#')).collect();
    assert_eq!(poses.len(), 8);
    std::fs::write(d.join("second.txt"), poses[4..].join("\n")).unwrap();
    let common = ["--voxel", "0.04", "--backend", "cpu"];
    let mut args = vec!["mesh", "seq", "--poses", "seq/groundtruth.txt"];
    args.extend(common);
    args.extend(["--out", "full.ply", "--save-volume", "full.tsdf"]);
    let summary = ok(&args);
    assert!(
        summary.contains("MB per square metre of surface"),
        "{summary}"
    );
    let mut args = vec!["mesh", "seq", "--poses", "seq/groundtruth.txt"];
    args.extend(common);
    args.extend(["--max-frames", "4", "--out", "half.ply"]);
    args.extend(["--save-volume", "half.tsdf"]);
    ok(&args);
    ok(&[
        "mesh",
        "seq",
        "--poses",
        "second.txt",
        "--volume",
        "half.tsdf",
        "--backend",
        "cpu",
        "--out",
        "resumed.ply",
        "--save-volume",
        "resumed.tsdf",
    ]);
    ok(&[
        "mesh",
        "--volume",
        "full.tsdf",
        "--backend",
        "cpu",
        "--out",
        "again.ply",
    ]);
    let read = |name: &str| std::fs::read(d.join(name)).unwrap();
    let full = read("full.ply");
    assert!(full.len() > 10_000, "{} bytes", full.len());
    assert_ne!(full, read("half.ply"));
    assert!(full == read("resumed.ply"), "resumed mesh differs");
    assert!(full == read("again.ply"), "re-extracted mesh differs");
    assert!(
        read("full.tsdf") == read("resumed.tsdf"),
        "resumed volume differs"
    );
    // The volume's voxel size applies: --voxel with --volume is refused.
    let (success, text) = run(&[
        "mesh",
        "--volume",
        "full.tsdf",
        "--voxel",
        "0.02",
        "--out",
        "x.ply",
    ]);
    assert!(!success && text.contains("--voxel"), "{text}");
    let mut bytes = read("full.tsdf");
    bytes.truncate(bytes.len() / 2);
    std::fs::write(d.join("cut.tsdf"), bytes).unwrap();
    let (success, text) = run(&["mesh", "--volume", "cut.tsdf", "--out", "x.ply"]);
    assert!(!success, "{text}");
    assert!(
        text.contains("cut.tsdf") && text.contains("truncated"),
        "{text}"
    );
    assert!(!text.contains("panicked"), "{text}");
}
