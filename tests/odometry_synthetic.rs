//! Odometry on rendered views of procedural scenes with exact ground truth.

use glam::DVec3;
use rgbid::camera::PinholeCamera;
use rgbid::geometry::Se3;
use rgbid::gpu::ComputeBackend;
use rgbid::image::RgbdFrame;
use rgbid::odometry::{
    CovarianceGradients, Estimator, GeometricSampling, Linearisation, Location, Odometry,
    OdometryConfig, Terms,
};
use rgbid::synth::trajectory::camera_pose;
use rgbid::synth::{render_pinhole, Scene, SensorModel};

fn camera() -> PinholeCamera {
    PinholeCamera::new(262.5, 262.5, 159.5, 119.5, 320, 240)
}

/// Two noiseless views `motion` apart: returns (reference, current, true cur_from_ref).
fn views(motion: &[f64; 6], noise: bool) -> (RgbdFrame, RgbdFrame, Se3) {
    let scene = Scene::preset("office", 3).expect("preset");
    let c = scene.free_area().center();
    let world_from_ref = camera_pose(DVec3::new(c.x - 0.8, c.y - 0.3, 1.4), 0.6, -0.15, 0.0);
    let ref_from_cur = Se3::exp(motion);
    let world_from_cur = world_from_ref * ref_from_cur;
    let sensor = if noise {
        SensorModel::kinect()
    } else {
        SensorModel::noiseless()
    };
    let a = render_pinhole(&scene, &camera(), &world_from_ref, &sensor, 1).to_rgbd_frame(0.0);
    let b =
        render_pinhole(&scene, &camera(), &world_from_cur, &sensor, 2).to_rgbd_frame(1.0 / 30.0);
    (a, b, ref_from_cur.inverse())
}

fn errors(est: &Se3, truth: &Se3) -> (f64, f64) {
    let e = truth.inverse() * *est;
    (e.translation.length() * 1e3, e.angle().to_degrees())
}

const MOTION: [f64; 6] = [0.02, -0.01, 0.015, 0.01, -0.015, 0.008];

/// Aligns two noisy views `MOTION` apart on `backend`, linearised as `linearisation`, and
/// checks the error.
fn known_motion_is_recovered(backend: &ComputeBackend, linearisation: Linearisation) {
    let (a, b, truth) = views(&MOTION, true);
    let cfg = OdometryConfig {
        linearisation,
        ..Default::default()
    };
    let mut odo = Odometry::new(cfg, camera(), backend).expect("odometry");
    let al = odo.align(&a, &b, Se3::IDENTITY).expect("align");
    let (mm, deg) = errors(&al.cur_from_ref, &truth);
    println!(
        "{} {linearisation:?}: error {mm:.3} mm {deg:.4} deg",
        backend.name()
    );
    assert!(
        mm < 1.0 && deg < 0.05,
        "{}: {mm} mm {deg} deg",
        backend.name()
    );
    assert!(al.covariance.is_some() && al.condition_number.is_finite());
}

#[test]
fn known_motion_is_recovered_on_the_cpu_backend() {
    known_motion_is_recovered(&ComputeBackend::Cpu, Linearisation::Current);
}

#[test]
fn reference_linearisation_recovers_known_motion() {
    known_motion_is_recovered(&ComputeBackend::Cpu, Linearisation::Reference);
}

#[test]
#[ignore = "needs a GPU adapter"]
fn gpu_known_motion_is_recovered_on_the_gpu_backend() {
    let Some(g) = rgbid::gpu::test_gpu("gpu_known_motion_is_recovered_on_the_gpu_backend") else {
        return;
    };
    known_motion_is_recovered(&ComputeBackend::Gpu(g), Linearisation::Current);
}

#[test]
#[ignore = "known gap: with the default nearest-pixel inverse-depth sampling, noiseless views converge to a ~1.3 mm bias (GeometricSampling::Linear: 0.01 mm, test below)"]
fn known_gap_known_motion_without_noise() {
    let (a, b, truth) = views(&MOTION, false);
    let mut odo =
        Odometry::new(OdometryConfig::default(), camera(), &ComputeBackend::Cpu).expect("odometry");
    let al = odo.align(&a, &b, Se3::IDENTITY).expect("align");
    let (mm, deg) = errors(&al.cur_from_ref, &truth);
    println!("noiseless: error {mm:.3} mm {deg:.4} deg");
    assert!(mm < 1.0 && deg < 0.05, "{mm} mm {deg} deg");
}

/// Replaces 20 % of the current frame by an object that moves on its own: a textured patch
/// taken from elsewhere in the image, 0.9 m from the camera.
fn add_moving_object(f: &mut RgbdFrame) {
    let (w, h) = (f.width(), f.height());
    let (ow, oh) = ((w as f64 * 0.5) as usize, (h as f64 * 0.4) as usize);
    let (x0, y0) = (w / 4, h / 3);
    let src = f.intensity().clone();
    for y in 0..oh {
        for x in 0..ow {
            let (dx, dy) = (x0 + x, y0 + y);
            let (sx, sy) = ((x * 7 + 13) % w, (y * 5 + 3) % h);
            f.intensity_mut().data_mut()[dy * w + dx] = src.data()[sy * w + sx];
            f.inverse_depth_mut().data_mut()[dy * w + dx] = 1.0 / 0.9;
        }
    }
}

/// A global brightness change between the views (an exposure step of 25 levels): with the
/// photometric term alone, the estimated location (eq. 4.26-4.27) absorbs it and the motion is
/// recovered; at zero location the offset pulls the pose.
#[test]
fn estimated_location_absorbs_a_brightness_change() {
    let (a, mut b, truth) = views(&MOTION, true);
    for v in b.intensity_mut().data_mut() {
        *v = (*v + 25.0).min(255.0);
    }
    let mut res = Vec::new();
    for location in [Location::Photometric, Location::Zero] {
        let cfg = OdometryConfig {
            terms: Terms::Photometric,
            location,
            ..Default::default()
        };
        let mut odo = Odometry::new(cfg, camera(), &ComputeBackend::Cpu).expect("odometry");
        let al = odo.align(&a, &b, Se3::IDENTITY).expect("align");
        let e = errors(&al.cur_from_ref, &truth);
        println!(
            "location {location:?}, intensity + 25: {:.3} mm {:.4} deg",
            e.0, e.1
        );
        res.push(e);
    }
    let (located, zero) = (res[0], res[1]);
    assert!(located.0 < 1.0 && located.1 < 0.05, "located: {located:?}");
    assert!(
        zero.0 > 3.0 * located.0.max(0.2) || zero.1 > 3.0 * located.1.max(0.01),
        "the offset did not hurt the zero location: {zero:?} vs {located:?}"
    );
}

#[test]
fn student_t_rejects_a_moving_object_that_least_squares_cannot() {
    let (a, mut b, truth) = views(&MOTION, false);
    add_moving_object(&mut b);
    let mut res = Vec::new();
    for est in [Estimator::Student, Estimator::LeastSquares] {
        let cfg = OdometryConfig {
            estimator: est,
            ..Default::default()
        };
        let mut odo = Odometry::new(cfg, camera(), &ComputeBackend::Cpu).expect("odometry");
        let al = odo.align(&a, &b, Se3::IDENTITY).expect("align");
        let e = errors(&al.cur_from_ref, &truth);
        println!(
            "{est:?} with a moving object over 20 % of the image: {:.3} mm {:.4} deg",
            e.0, e.1
        );
        res.push(e);
    }
    let (s, l) = (res[0], res[1]);
    assert!(s.0 < 1.0 && s.1 < 0.05, "Student-t: {s:?}");
    assert!(
        l.0 > 5.0 * s.0.max(0.2) || l.1 > 5.0 * s.1.max(0.01),
        "least squares was not hurt: {l:?} vs {s:?}"
    );
}

#[test]
fn tracking_a_rendered_sequence_switches_references_and_stays_accurate() {
    let scene = Scene::preset("office", 5).expect("preset");
    let c = scene.free_area().center();
    let mut odo =
        Odometry::new(OdometryConfig::default(), camera(), &ComputeBackend::Cpu).expect("odometry");
    let start = camera_pose(DVec3::new(c.x, c.y, 1.5), 0.0, -0.1, 0.0);
    odo.set_initial_pose(start);
    let mut switches = 0;
    let mut last = Se3::IDENTITY;
    let mut truth = start;
    for k in 0..30 {
        // A slow turn with a little forward motion: 1 cm and 0.6 deg per frame.
        truth = start * Se3::exp(&[0.0, 0.0, 0.01 * k as f64, 0.0, 0.0105 * k as f64, 0.0]);
        let f = render_pinhole(&scene, &camera(), &truth, &SensorModel::kinect(), k)
            .to_rgbd_frame(k as f64 / 30.0);
        let r = odo.track(&f).expect("track");
        switches += usize::from(r.stats.new_reference);
        last = r.world_from_camera;
    }
    let (mm, deg) = errors(&last, &truth);
    println!("after 30 frames: drift {mm:.2} mm {deg:.3} deg, {switches} reference frames");
    assert!((2..30).contains(&switches), "{switches} reference frames");
    assert!(mm < 15.0 && deg < 0.5, "{mm} mm {deg} deg");
}

/// The bilateral covariance pass on `backend` (filtering the frame that `linearisation`
/// differentiates): same pose, larger covariance.
fn bilateral_covariance_pass(backend: &ComputeBackend, linearisation: Linearisation) {
    let (a, b, truth) = views(&MOTION, true);
    let mut out = Vec::new();
    for covariance in [CovarianceGradients::Raw, CovarianceGradients::Bilateral] {
        let cfg = OdometryConfig {
            covariance,
            linearisation,
            ..Default::default()
        };
        let mut odo = Odometry::new(cfg, camera(), backend).expect("odometry");
        let al = odo.align(&a, &b, Se3::IDENTITY).expect("align");
        let c = al.covariance.expect("covariance");
        let trace = (0..6).map(|i| c.rows()[i][i]).sum::<f64>();
        println!(
            "{} {linearisation:?} {covariance:?}: trace {trace:.3e}, condition {:.3e}, covariance pass {:.2} ms",
            backend.name(),
            al.condition_number,
            al.times.covariance_ms
        );
        assert!(al.condition_number.is_finite());
        out.push((al.cur_from_ref, trace));
    }
    // Same estimate (the pass only evaluates the Hessian), and smoothed gradients carry
    // less information: a larger covariance.
    assert_eq!(out[0].0.log(), out[1].0.log());
    assert!(out[1].1 > out[0].1, "{} vs {}", out[1].1, out[0].1);
    let (mm, deg) = errors(&out[1].0, &truth);
    assert!(mm < 1.0 && deg < 0.05, "{mm} mm {deg} deg");
}

#[test]
fn bilateral_covariance_pass_changes_the_covariance_not_the_pose() {
    bilateral_covariance_pass(&ComputeBackend::Cpu, Linearisation::Current);
}

#[test]
fn reference_bilateral_covariance_pass_changes_the_covariance_not_the_pose() {
    bilateral_covariance_pass(&ComputeBackend::Cpu, Linearisation::Reference);
}

#[test]
#[ignore = "needs a GPU adapter"]
fn gpu_bilateral_covariance_pass_changes_the_covariance_not_the_pose() {
    let test = "gpu_bilateral_covariance_pass_changes_the_covariance_not_the_pose";
    let Some(g) = rgbid::gpu::test_gpu(test) else {
        return;
    };
    bilateral_covariance_pass(&ComputeBackend::Gpu(g), Linearisation::Current);
}

/// First-order inverse-depth sampling on `backend`, linearised as `linearisation`:
/// noiseless views give the exact motion.
fn first_order_sampling(backend: &ComputeBackend, linearisation: Linearisation) {
    // The nearest-pixel geometric residual leaves a bias on noiseless views (the known gap
    // above); extending the nearest sample along its gradient removes it.
    let (a, b, truth) = views(&MOTION, false);
    let cfg = OdometryConfig {
        geometric_sampling: GeometricSampling::Linear,
        linearisation,
        ..Default::default()
    };
    let mut odo = Odometry::new(cfg, camera(), backend).expect("odometry");
    let al = odo.align(&a, &b, Se3::IDENTITY).expect("align");
    let (mm, deg) = errors(&al.cur_from_ref, &truth);
    println!(
        "{} {linearisation:?}, linear sampling, noiseless: {mm:.4} mm {deg:.5} deg",
        backend.name()
    );
    assert!(
        mm < 0.1 && deg < 0.005,
        "{}: {mm} mm {deg} deg",
        backend.name()
    );
}

#[test]
fn first_order_inverse_depth_sampling_recovers_noiseless_motion() {
    first_order_sampling(&ComputeBackend::Cpu, Linearisation::Current);
}

#[test]
fn reference_linearisation_recovers_noiseless_motion() {
    first_order_sampling(&ComputeBackend::Cpu, Linearisation::Reference);
}

#[test]
#[ignore = "needs a GPU adapter"]
fn gpu_first_order_inverse_depth_sampling_recovers_noiseless_motion() {
    let test = "gpu_first_order_inverse_depth_sampling_recovers_noiseless_motion";
    let Some(g) = rgbid::gpu::test_gpu(test) else {
        return;
    };
    for lin in [Linearisation::Current, Linearisation::Reference] {
        first_order_sampling(&ComputeBackend::Gpu(g.clone()), lin);
    }
}
