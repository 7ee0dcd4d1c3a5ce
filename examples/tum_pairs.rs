//! Aligns the two real TUM pairs of `../shared/data/rgbd/tum_pairs` with the odometry
//! configuration of each JSON file given (an `OdometryConfig`; `{}` = the defaults) and prints
//! the error of `prev_from_cur` against ground truth (the thesis-claims table in docs/notes.md):
//! `cargo run --release --example tum_pairs -- a.json b.json`.

use rgbid::camera::PinholeCamera;
use rgbid::geometry::Se3;
use rgbid::gpu::ComputeBackend;
use rgbid::odometry::*;

fn main() {
    let cam = PinholeCamera::new(525.0, 525.0, 319.5, 239.5, 640, 480);
    for cfg_path in std::env::args().skip(1) {
        let cfg = match OdometryConfig::from_json_file(std::path::Path::new(&cfg_path)) {
            Ok(c) => c,
            Err(e) => {
                eprintln!("{e}");
                std::process::exit(2);
            }
        };
        for case in ["case_1", "case_2"] {
            let dir = std::path::Path::new("../shared/data/rgbd/tum_pairs").join(case);
            let load = |a: &str, b: &str| {
                rgbid::io::load_pair_frame(&dir.join(a), &dir.join(b), &cam, 5000.0).unwrap()
            };
            let prev = load("img_prev.png", "dep_prev.png");
            let cur = load("img_curr.png", "dep_curr.png");
            let pose = |p: &str| rgbid::io::read_pose_file(&dir.join(p)).unwrap();
            let truth = pose("pose_prev.txt").inverse() * pose("pose_curr.txt");
            let mut odo = Odometry::new(cfg.clone(), cam, &ComputeBackend::Cpu).unwrap();
            let a = odo.align(&prev, &cur, Se3::IDENTITY).unwrap();
            let err = truth.inverse() * a.cur_from_ref.inverse();
            let w = err.log();
            println!(
                "{cfg_path} {case}: {:.2} mm {:.3} deg (error rotation vector, deg: {:+.3} {:+.3} {:+.3})",
                err.translation.length() * 1e3,
                err.angle().to_degrees(),
                w[3].to_degrees(),
                w[4].to_degrees(),
                w[5].to_degrees()
            );
            let e = a.cur_from_ref.inverse();
            let v = e.log();
            println!(
                "    estimate prev_from_cur: t {:+.3} {:+.3} {:+.3} mm, rotation vector {:+.4} {:+.4} {:+.4} deg",
                e.translation.x * 1e3,
                e.translation.y * 1e3,
                e.translation.z * 1e3,
                v[3].to_degrees(),
                v[4].to_degrees(),
                v[5].to_degrees()
            );
        }
    }
}
