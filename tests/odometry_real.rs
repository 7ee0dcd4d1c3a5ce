//! Odometry on real data from `../shared/data` (ignored by default: run with `--ignored`).

mod common;

use rgbid::camera::PinholeCamera;
use rgbid::geometry::Se3;
use rgbid::gpu::ComputeBackend;
use rgbid::image::RgbdFrame;
use rgbid::odometry::{Odometry, OdometryConfig};

fn load(rgb: &std::path::Path, depth: &std::path::Path, cam: &PinholeCamera) -> RgbdFrame {
    rgbid::io::load_pair_frame(rgb, depth, cam, 5000.0).expect("tum pair frame")
}

fn pose(path: &std::path::Path) -> Se3 {
    rgbid::io::read_pose_file(path).expect("pose file")
}

#[test]
#[ignore = "known gap: rotation ~10 % behind OpenCV; needs ../shared/data"]
fn known_gap_real_data_tum_pairs_match_opencv() {
    let _ = env_logger::builder().is_test(true).try_init();
    let cam = PinholeCamera::new(525.0, 525.0, 319.5, 239.5, 640, 480);
    let mut failures = 0;
    for case in ["case_1", "case_2"] {
        let dir = common::shared_data().join("rgbd/tum_pairs").join(case);
        let prev = load(&dir.join("img_prev.png"), &dir.join("dep_prev.png"), &cam);
        let cur = load(&dir.join("img_curr.png"), &dir.join("dep_curr.png"), &cam);
        let world_from_prev = pose(&dir.join("pose_prev.txt"));
        let world_from_cur = pose(&dir.join("pose_curr.txt"));
        let truth_prev_from_cur = world_from_prev.inverse() * world_from_cur;
        if std::env::var("RGBID_EXPLORE").is_ok() {
            use rgbid::odometry::*;
            let variants: Vec<(&str, OdometryConfig)> = vec![
                (
                    "iters 10/10/20",
                    OdometryConfig {
                        iterations: vec![10, 10, 20],
                        ..Default::default()
                    },
                ),
                (
                    "iters 20/20/30",
                    OdometryConfig {
                        iterations: vec![20, 20, 30],
                        ..Default::default()
                    },
                ),
                (
                    "huber",
                    OdometryConfig {
                        estimator: Estimator::Huber,
                        iterations: vec![20, 20, 30],
                        ..Default::default()
                    },
                ),
                (
                    "photo",
                    OdometryConfig {
                        terms: Terms::Photometric,
                        iterations: vec![20, 20, 30],
                        ..Default::default()
                    },
                ),
                (
                    "geo",
                    OdometryConfig {
                        terms: Terms::Geometric,
                        iterations: vec![20, 20, 30],
                        ..Default::default()
                    },
                ),
                (
                    "4 levels",
                    OdometryConfig {
                        levels: 4,
                        iterations: vec![10, 10, 20, 30],
                        ..Default::default()
                    },
                ),
                (
                    "mad",
                    OdometryConfig {
                        scale: ScaleMethod::Mad,
                        iterations: vec![20, 20, 30],
                        ..Default::default()
                    },
                ),
                (
                    "fixed",
                    OdometryConfig {
                        scale: ScaleMethod::Fixed,
                        iterations: vec![20, 20, 30],
                        ..Default::default()
                    },
                ),
            ];
            for (name, cfg) in variants {
                let mut odo = Odometry::new(cfg, cam, &ComputeBackend::Cpu).unwrap();
                let a = odo.align(&prev, &cur, Se3::IDENTITY).unwrap();
                let err = truth_prev_from_cur.inverse() * a.cur_from_ref.inverse();
                let its: Vec<usize> = a.levels.iter().map(|l| l.iterations).collect();
                println!(
                    "  {case} {name}: {:.2} mm {:.3} deg its {its:?} nu {:.2}",
                    err.translation.length() * 1e3,
                    err.angle().to_degrees(),
                    a.levels.last().unwrap().nu_photo
                );
            }
        }
        let mut odo = Odometry::new(OdometryConfig::default(), cam, &ComputeBackend::Cpu).unwrap();
        let a = odo.align(&prev, &cur, Se3::IDENTITY).unwrap();
        let est_prev_from_cur = a.cur_from_ref.inverse();
        let err = truth_prev_from_cur.inverse() * est_prev_from_cur;
        println!(
            "{case}: true {:.1} mm {:.2} deg; error {:.2} mm {:.3} deg; {:?}",
            truth_prev_from_cur.translation.length() * 1e3,
            truth_prev_from_cur.angle().to_degrees(),
            err.translation.length() * 1e3,
            err.angle().to_degrees(),
            a.levels
        );
        println!("  times {:?}", a.times);
        // The bar: no worse than OpenCV 5 RGB_DEPTH (5.7 / 5.2 mm, 0.158 / 0.158 deg,
        // data README). Known gap: rgbid's rotation error is ~10 % higher (0.177 / 0.164 deg).
        failures +=
            usize::from(!(err.translation.length() < 0.0057 && err.angle().to_degrees() < 0.158));
    }
    assert_eq!(
        failures, 0,
        "pairs where OpenCV RGB_DEPTH was more accurate"
    );
}

/// Default odometry (CPU backend) over all 300 frames of redkitchen, evaluated against its
/// ground truth.
fn redkitchen_default_metrics() -> rgbid::eval::TrajectoryMetrics {
    default_metrics("redkitchen_0_299", None)
}

/// The default odometry (CPU) over a sequence of `../shared/data/rgbd`, with a camera preset
/// or the sequence's own camera, scored against its ground truth.
fn default_metrics(name: &str, preset: Option<&str>) -> rgbid::eval::TrajectoryMetrics {
    use rgbid::io::tum::{OpenOptions, TumSequence};
    let dir = common::shared_data().join("rgbd").join(name);
    let options = OpenOptions {
        camera: preset.map(|p| p.parse().expect("camera preset")),
        ..OpenOptions::default()
    };
    let seq = TumSequence::open(&dir, &options).expect(name);
    let gt_path = seq.groundtruth.clone().expect("ground truth");
    let gt = rgbid::io::trajectory::read_tum(&gt_path).expect("ground truth");
    let mut odo = Odometry::new(OdometryConfig::default(), seq.camera, &ComputeBackend::Cpu)
        .expect("odometry");
    let mut est = Vec::new();
    for i in 0..seq.len() {
        let f = seq.load(i).expect("frame");
        if i == 0 {
            // The first estimate at the ground truth's first pose, as the CLI does.
            odo.set_initial_pose(gt[0].world_from_camera);
        }
        let r = odo.track(&f).expect("track");
        est.push(rgbid::trajectory::TimedPose {
            timestamp: f.timestamp(),
            world_from_camera: r.world_from_camera,
        });
    }
    rgbid::eval::evaluate(&gt, &est, &rgbid::eval::EvalOptions::default()).expect("eval")
}

/// The rotational RPE (RMSE over 1 s windows) of OpenCV 5 RGB_DEPTH on redkitchen, 1.958
/// deg/s, from `rgbid bench odometry ... --peers cv_rgbd` (its trajectory scored by rgbid's
/// evaluator). rgbid is at 1.973 deg/s, 0.8 % behind, while its mean and median are lower
/// (docs/notes.md, odometry: rotation on redkitchen).
#[test]
#[ignore = "known gap: rotational RPE 0.8 % behind OpenCV; needs ../shared/data"]
fn known_gap_real_data_redkitchen_rotation_rpe_matches_opencv() {
    let m = redkitchen_default_metrics();
    let rot = m.rpe.expect("1 s pairs").rotation_deg_per_s.rmse;
    println!("redkitchen 300 frames: rotational RPE {rot:.4} deg/s");
    assert!(
        rot <= 1.958,
        "rotational RPE {rot} deg/s worse than OpenCV RGB_DEPTH (1.958 deg/s)"
    );
}

/// The bar on the named sequence: with the default configuration, the CPU backend's
/// ATE and RPE over all 300 frames of redkitchen are no worse than OpenCV 5 RGB_DEPTH's
/// (0.033 m and 0.035 m/s, `../shared/data/README.md`, the same sequence and metrics). Measured
/// here: 0.0301 m and 0.0348 m/s.
#[test]
#[ignore = "needs ../shared/data (runs in CI's real-data stage)"]
fn real_data_redkitchen_default_odometry_is_no_worse_than_opencv() {
    let m = redkitchen_default_metrics();
    let ate = m.ate.translation.rmse;
    let rpe = m.rpe.expect("1 s pairs").translation_m_per_s.rmse;
    println!("redkitchen 300 frames: ATE {ate:.4} m, RPE {rpe:.4} m/s");
    assert!(
        ate <= 0.033,
        "ATE {ate} m worse than OpenCV RGB_DEPTH (0.033 m)"
    );
    assert!(
        rpe <= 0.035,
        "RPE {rpe} m/s worse than OpenCV RGB_DEPTH (0.035 m/s)"
    );
}

/// The bar on TUM fr1/rpy frames 0-199 (camera `tum_fr1`): with the default
/// configuration, ATE and RPE no worse than OpenCV 5 RGB_DEPTH's on the same frames (0.0400 m
/// and 0.0476 m/s, `scripts/thesis_tables.sh`, docs/results.md: its trajectory scored by
/// rgbid's evaluator).
#[test]
#[ignore = "needs ../shared/data (runs in CI's real-data stage)"]
fn real_data_fr1_rpy_default_odometry_is_no_worse_than_opencv() {
    let m = default_metrics("tum_fr1_rpy_0_199", Some("tum_fr1"));
    let ate = m.ate.translation.rmse;
    let rpe = m.rpe.expect("1 s pairs").translation_m_per_s.rmse;
    println!("fr1/rpy 200 frames: ATE {ate:.4} m, RPE {rpe:.4} m/s");
    assert!(
        ate <= 0.0400,
        "ATE {ate} m worse than OpenCV RGB_DEPTH (0.0400 m)"
    );
    assert!(
        rpe <= 0.0476,
        "RPE {rpe} m/s worse than OpenCV RGB_DEPTH (0.0476 m/s)"
    );
}
