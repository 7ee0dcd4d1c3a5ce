//! Monocular EKF SLAM on real images: the 7-Scenes redkitchen colour images (frames 0-299,
//! Kinect RGB, 640x480, f = 585 px) from `../shared/data`, used as an image-only sequence.
//! The Sim(3)-aligned error must stay well below the spread of the ground-truth positions
//! (0.33 m) that a lost or frozen filter would show.

use std::path::Path;

use rgbid::camera::UnifiedCamera;
use rgbid::eval::ate::ate;
use rgbid::io::trajectory::read_tum;
use rgbid::mono::{ImageSequence, MonoConfig, MonoSlam};
use rgbid::trajectory::TimedPose;

#[test]
#[ignore = "needs ../shared/data"]
fn redkitchen_images_track_with_bounded_similarity_error() {
    let dir = Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../shared/data"))
        .join("rgbd/redkitchen_0_299");
    let seq = ImageSequence::open(&dir).expect("sequence");
    let camera = UnifiedCamera::new(0.0, 585.0, 320.0, 240.0, 640, 480);
    let mut slam = MonoSlam::new(camera, MonoConfig::default()).expect("filter");
    let mut est = Vec::new();
    for i in 0..seq.len() {
        let (t, img) = seq.load(i).expect("index").expect("image");
        let r = slam.process(t, &img).expect("frame");
        est.push(TimedPose {
            timestamp: t,
            world_from_camera: r.world_from_camera,
        });
    }
    let gt = read_tum(&dir.join("groundtruth.txt")).expect("ground truth");
    let pairs = rgbid::eval::associate(&est, &gt, 0.02);
    assert_eq!(pairs.len(), est.len());
    let e: Vec<TimedPose> = pairs.iter().map(|p| est[p.0]).collect();
    let g: Vec<TimedPose> = pairs.iter().map(|p| gt[p.1]).collect();
    let a = ate(&g, &e, true).expect("ate");
    let s = slam.stats();
    eprintln!(
        "redkitchen mono: ATE rmse {:.4} m (Sim(3), scale {:.3}), FI {}, Rm {:.2}",
        a.translation.rmse,
        a.alignment.scale,
        s.features_initialised,
        s.rm()
    );
    assert!(a.translation.rmse < 0.16, "ATE {} m", a.translation.rmse);
}
