//! Trajectory evaluation: exact answers on synthetic trajectories, the CLI, and (ignored) a
//! cross-check against the independent Python implementation on real ground truth.

use std::path::{Path, PathBuf};

use glam::{DQuat, DVec3};
use rgbid::eval::{evaluate, EvalError, EvalOptions, RpeDelta};
use rgbid::geometry::Se3;
use rgbid::io::trajectory::{read_tum, write_tum};
use rgbid::trajectory::TimedPose;

fn helix(n: usize, dt: f64) -> Vec<TimedPose> {
    (0..n)
        .map(|i| {
            let t = i as f64 * dt;
            TimedPose {
                timestamp: 100.0 + t,
                world_from_camera: Se3::new(
                    DQuat::from_euler(
                        glam::EulerRot::ZYX,
                        0.3 * t,
                        0.1 * (t * 0.7).sin(),
                        0.05 * t.cos(),
                    ),
                    DVec3::new(t.cos(), t.sin(), 0.2 * t),
                ),
            }
        })
        .collect()
}

#[test]
fn rigidly_moved_estimate_has_zero_error() {
    let gt = helix(200, 1.0 / 30.0);
    let offset = Se3::new(DQuat::from_rotation_y(0.7), DVec3::new(3.0, -1.0, 0.5));
    // Same trajectory in another world frame, time stamps jittered by up to 5 ms.
    let est: Vec<TimedPose> = gt
        .iter()
        .enumerate()
        .map(|(i, p)| TimedPose {
            timestamp: p.timestamp + 0.005 * ((i % 3) as f64 - 1.0),
            world_from_camera: offset * p.world_from_camera,
        })
        .collect();
    let m = evaluate(&gt, &est, &EvalOptions::default()).unwrap();
    assert_eq!(m.matched, 200);
    assert!(m.ate.translation.rmse < 1e-9, "{:?}", m.ate);
    let rpe = m.rpe.unwrap();
    assert!(rpe.translation_m.max < 1e-9 && rpe.rotation_deg.max < 1e-5);
    assert!(rpe.pairs > 160 && rpe.pairs < 175, "{}", rpe.pairs);
    assert_eq!(m.rpe_frame.unwrap().pairs, 199);
    // Path of the helix: 200 steps of ~sqrt(1 + 0.04)/30 m.
    assert!((m.path_length_m - 199.0 / 30.0 * 1.04f64.sqrt()).abs() < 1e-3);
}

#[test]
fn scaled_estimate_needs_sim3() {
    let gt = helix(100, 0.05);
    let est: Vec<TimedPose> = gt
        .iter()
        .map(|p| TimedPose {
            timestamp: p.timestamp,
            world_from_camera: Se3::new(
                p.world_from_camera.rotation,
                0.4 * p.world_from_camera.translation,
            ),
        })
        .collect();
    let rigid = evaluate(&gt, &est, &EvalOptions::default()).unwrap();
    assert!(rigid.ate.translation.rmse > 0.1);
    let sim = evaluate(
        &gt,
        &est,
        &EvalOptions {
            with_scale: true,
            ..Default::default()
        },
    )
    .unwrap();
    assert!(sim.ate.translation.rmse < 1e-9);
    assert!((sim.ate.alignment.scale - 2.5).abs() < 1e-9);
}

#[test]
fn constant_velocity_error_gives_known_rpe() {
    // The estimate overshoots every step by 1 cm along the camera's x axis (which is the
    // world x axis here: no rotation): RPE over 1 s (10 steps of 0.1 s) is 10 cm.
    let gt: Vec<TimedPose> = (0..60)
        .map(|i| TimedPose {
            timestamp: i as f64 * 0.1,
            world_from_camera: Se3::new(DQuat::IDENTITY, DVec3::new(0.05 * i as f64, 0.0, 0.0)),
        })
        .collect();
    let est: Vec<TimedPose> = gt
        .iter()
        .enumerate()
        .map(|(i, p)| TimedPose {
            timestamp: p.timestamp,
            world_from_camera: Se3::new(DQuat::IDENTITY, DVec3::new(0.06 * i as f64, 0.0, 0.0)),
        })
        .collect();
    let m = evaluate(&gt, &est, &EvalOptions::default()).unwrap();
    let r = m.rpe.unwrap();
    // t_k is the first stamp >= t_i + 1, so dt is 1.0 s (or 1.1 s where float rounding of
    // i * 0.1 + 1 pushes past a stamp): errors 0.10 or 0.11 m; per second exactly 0.1 m/s.
    assert!(r.translation_m.min >= 0.1 - 1e-9 && r.translation_m.max <= 0.11 + 1e-9);
    assert!(
        (r.translation_m_per_s.rmse - 0.1).abs() < 1e-9,
        "{:?}",
        r.translation_m_per_s
    );
    assert!((r.translation_m_per_s.max - 0.1).abs() < 1e-9);
    assert!(r.rotation_deg.max == 0.0);
    let f = m.rpe_frame.unwrap();
    assert!(
        (f.translation_m.mean - 0.01).abs() < 1e-12
            && (f.translation_m_per_s.mean - 0.1).abs() < 1e-9
    );
    // Frames mode with n = 10 reproduces the 1 s figure exactly.
    let r10 = rgbid::eval::rpe(&gt, &est, RpeDelta::Frames(10))
        .unwrap()
        .unwrap();
    assert!((r10.translation_m.rmse - 0.1).abs() < 1e-12);
}

#[test]
fn too_few_matches_is_an_error() {
    let gt = helix(10, 0.1);
    let est: Vec<TimedPose> = gt
        .iter()
        .map(|p| TimedPose {
            timestamp: p.timestamp + 0.05,
            ..*p
        })
        .collect();
    match evaluate(&gt, &est, &EvalOptions::default()) {
        Err(EvalError::TooFewMatches { matched: 0, .. }) => {}
        other => panic!("{other:?}"),
    }
    assert!(evaluate(
        &gt,
        &est,
        &EvalOptions {
            max_time_difference: 0.06,
            ..Default::default()
        }
    )
    .is_ok());
    let bad = EvalOptions {
        delta: RpeDelta::Seconds(0.0),
        ..Default::default()
    };
    assert!(matches!(
        evaluate(&gt, &gt, &bad),
        Err(EvalError::InvalidOption { .. })
    ));
}

#[test]
fn cli_prints_json_and_table() {
    let tmp = tempfile::tempdir().unwrap();
    let gt = helix(90, 1.0 / 30.0);
    let est: Vec<TimedPose> = gt
        .iter()
        .map(|p| TimedPose {
            timestamp: p.timestamp,
            world_from_camera: Se3::new(
                p.world_from_camera.rotation,
                p.world_from_camera.translation + DVec3::X * 0.5,
            ),
        })
        .collect();
    write_tum(&tmp.path().join("gt.txt"), &gt).unwrap();
    write_tum(&tmp.path().join("est.txt"), &est).unwrap();
    let exe = env!("CARGO_BIN_EXE_rgbid");
    let out = std::process::Command::new(exe)
        .args(["eval", "--json"])
        .arg(tmp.path().join("gt.txt"))
        .arg(tmp.path().join("est.txt"))
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(v["matched"], 90);
    assert!(v["ate"]["translation"]["rmse"].as_f64().unwrap() < 1e-6);
    let out = std::process::Command::new(exe)
        .arg("eval")
        .arg(tmp.path().join("gt.txt"))
        .arg(tmp.path().join("missing.txt"))
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("missing.txt"));
    let out = std::process::Command::new(exe)
        .arg("eval")
        .arg(tmp.path().join("gt.txt"))
        .arg(tmp.path().join("est.txt"))
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        text.contains("ATE m") && text.contains("RPE 1s m/s"),
        "{text}"
    );
}

fn perturbed(gt: &[TimedPose], seed: u64) -> Vec<TimedPose> {
    // Deterministic drift + noise + a time offset of 4 ms.
    let mut s = seed;
    let mut rnd = move || {
        s = s
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((s >> 11) as f64 / (1u64 << 53) as f64) - 0.5
    };
    let mut drift = Se3::IDENTITY;
    let mut out = Vec::new();
    let mut prev = gt[0].world_from_camera;
    let mut est_pose = Se3::new(DQuat::from_rotation_z(0.3), DVec3::new(1.0, 2.0, 0.5)) * prev;
    for p in gt {
        let step = prev.inverse() * p.world_from_camera;
        prev = p.world_from_camera;
        let noise = Se3::exp(&[
            0.002 * rnd(),
            0.002 * rnd(),
            0.002 * rnd(),
            0.003 * rnd(),
            0.003 * rnd(),
            0.003 * rnd(),
        ]);
        drift = drift * Se3::exp(&[0.0002, 0.0, 0.0001, 0.0, 0.0003, 0.0]);
        est_pose = est_pose * step * noise;
        out.push(TimedPose {
            timestamp: p.timestamp + 0.004,
            world_from_camera: est_pose * drift,
        });
    }
    out
}

/// Python with numpy and scipy: `$RGBID_PYTHON` (set by `.ci/run`), else `../.venv-peers`.
fn python() -> Option<(PathBuf, PathBuf)> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let py = std::env::var_os("RGBID_PYTHON")
        .map(PathBuf::from)
        .unwrap_or_else(|| root.join(".venv-peers/bin/python"));
    let script = root.join("shared/eval/traj_metrics.py");
    (py.is_file() && script.is_file()).then_some((py, script))
}

#[test]
#[ignore = "needs ../shared/data"]
fn cross_check_against_python_reference_on_redkitchen() {
    let data = Path::new(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../shared/data/rgbd/redkitchen_0_299"
    ));
    let gt_path = data.join("groundtruth.txt");
    let gt = read_tum(&gt_path).unwrap();
    let Some((py, script)) = python() else {
        panic!("needs a Python with numpy+scipy ($RGBID_PYTHON or ../.venv-peers) and ../shared/eval/traj_metrics.py")
    };
    let tmp = tempfile::tempdir().unwrap();
    for (seed, scale, delta) in [(1u64, false, 1.0), (2, false, 0.5), (3, true, 1.0)] {
        let est_path = tmp.path().join(format!("est{seed}.txt"));
        let mut est = perturbed(&gt, seed);
        if scale {
            for p in &mut est {
                p.world_from_camera.translation *= 0.37;
            }
        }
        write_tum(&est_path, &est).unwrap();
        // Both sides read the written file, so they see the same rounded numbers.
        let est = read_tum(&est_path).unwrap();
        let mut cmd = std::process::Command::new(&py);
        cmd.arg(&script)
            .arg(&gt_path)
            .arg(&est_path)
            .args(["--delta", &delta.to_string()]);
        if scale {
            cmd.arg("--scale");
        }
        let out = cmd.output().unwrap();
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        let py_m: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
        let opts = EvalOptions {
            delta: RpeDelta::Seconds(delta),
            with_scale: scale,
            ..Default::default()
        };
        let m = evaluate(&gt, &est, &opts).unwrap();
        let rpe = m.rpe.as_ref().unwrap();
        // The script reports the per-pair error / dt * delta.
        let rpe_per_delta = rpe.translation_m_per_s.rmse * delta;
        let rel = |a: f64, b: f64| (a - b).abs() / b.abs().max(1e-12);
        let pairs = [
            ("ate_rmse", m.ate.translation.rmse),
            ("ate_median", m.ate.translation.median),
            ("ate_max", m.ate.translation.max),
            ("rpe_rmse_per_s", rpe_per_delta),
            ("path_m", m.path_length_m),
        ];
        assert_eq!(py_m["matched"].as_u64().unwrap() as usize, m.matched);
        for (k, ours) in pairs {
            let theirs = py_m[k].as_f64().unwrap();
            println!(
                "seed {seed} scale {scale} delta {delta}: {k} rust {ours:.9} python {theirs:.9}"
            );
            assert!(rel(ours, theirs) < 1e-6, "{k}: {ours} vs {theirs}");
        }
        assert!(
            m.ate.translation.rmse > 0.001,
            "the perturbation must be visible"
        );
    }
}
