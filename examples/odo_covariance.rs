//! Consistency of the odometry covariance on rendered views with exact ground truth: for
//! random motions between two views of generated scenes (Kinect-like noise), the normalised
//! estimation error squared NEES = e^T C^-1 e of the error twist e = log(true * est^-1)
//! (the covariance's left perturbation) with the covariance from raw gradients and from the
//! bilateral-filtered covariance pass. A consistent 6-dof covariance has mean NEES 6.
//! `cargo run --release --example odo_covariance -- [PAIRS] [--width W] [--config X.json] [--noiseless]`
//! (`--noiseless`: views without sensor noise, to see the estimator's bias).

use glam::DVec3;
use rgbid::camera::PinholeCamera;
use rgbid::geometry::Se3;
use rgbid::gpu::ComputeBackend;
use rgbid::odometry::{CovarianceGradients, Odometry, OdometryConfig};
use rgbid::synth::trajectory::camera_pose;
use rgbid::synth::{render_pinhole, Scene, SensorModel};

fn nees(e: &[f64; 6], c: &[[f64; 6]; 6]) -> f64 {
    let m = nalgebra::Matrix6::from_fn(|i, j| c[i][j]);
    let v = nalgebra::Vector6::from_column_slice(e);
    match m.cholesky() {
        Some(ch) => v.dot(&ch.solve(&v)),
        None => f64::NAN,
    }
}

fn main() -> anyhow::Result<()> {
    let mut pairs = 24usize;
    let mut width = 320u32;
    let mut base = OdometryConfig::default();
    let mut noiseless = false;
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        if a == "--noiseless" {
            noiseless = true;
        } else if a == "--width" {
            width = args.next().unwrap_or_default().parse()?;
        } else if a == "--config" {
            let path = args.next().unwrap_or_default();
            base = OdometryConfig::from_json_file(std::path::Path::new(&path))?;
        } else {
            pairs = a.parse()?;
        }
    }
    let s = f64::from(width) / 640.0;
    let cam = PinholeCamera::new(
        525.0 * s,
        525.0 * s,
        f64::from(width) / 2.0 - 0.5,
        f64::from(width) * 0.375 - 0.5,
        width,
        width * 3 / 4,
    );
    let mut rng = 12345u64;
    let mut uni = move || {
        rng = rng
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((rng >> 11) as f64) / ((1u64 << 53) as f64) * 2.0 - 1.0
    };
    let modes = [CovarianceGradients::Raw, CovarianceGradients::Bilateral];
    let mut rows: Vec<[f64; 6]> = Vec::new();
    println!("pair  err mm  err deg   NEES raw  NEES bilateral   sd_t raw/bilateral mm");
    for k in 0..pairs {
        let scene = Scene::preset(if k % 2 == 0 { "office" } else { "kitchen" }, k as u64)
            .map_err(|e| anyhow::anyhow!("{e}"))?;
        let c = scene.free_area().center();
        let world_from_ref = camera_pose(
            DVec3::new(c.x + 0.5 * uni(), c.y + 0.5 * uni(), 1.3 + 0.2 * uni()),
            3.0 * uni(),
            -0.15 + 0.1 * uni(),
            0.0,
        );
        let motion = [
            0.02 * uni(),
            0.02 * uni(),
            0.02 * uni(),
            0.015 * uni(),
            0.015 * uni(),
            0.015 * uni(),
        ];
        let world_from_cur = world_from_ref * Se3::exp(&motion);
        let sensor = if noiseless {
            SensorModel::noiseless()
        } else {
            SensorModel::kinect()
        };
        let a =
            render_pinhole(&scene, &cam, &world_from_ref, &sensor, 2 * k as u64).to_rgbd_frame(0.0);
        let b = render_pinhole(&scene, &cam, &world_from_cur, &sensor, 2 * k as u64 + 1)
            .to_rgbd_frame(1.0 / 30.0);
        let truth = world_from_cur.inverse() * world_from_ref;
        // err mm, err deg, NEES raw / bilateral, translation sd raw / bilateral (mm).
        let mut row = [0.0; 6];
        for (m, mode) in modes.iter().enumerate() {
            let cfg = OdometryConfig {
                covariance: *mode,
                ..base.clone()
            };
            let mut odo = Odometry::new(cfg, cam, &ComputeBackend::Cpu)?;
            let al = odo.align(&a, &b, Se3::IDENTITY)?;
            let err = truth * al.cur_from_ref.inverse();
            let cov = al.covariance.map_or([[f64::NAN; 6]; 6], |c| *c.rows());
            row[0] = err.translation.length() * 1e3;
            row[1] = err.angle().to_degrees();
            row[2 + m] = nees(&err.log(), &cov);
            row[4 + m] = (cov[0][0] + cov[1][1] + cov[2][2]).sqrt() * 1e3;
        }
        println!(
            "{k:4} {:7.3} {:8.4} {:10.1} {:15.1} {:10.3}/{:.3}",
            row[0], row[1], row[2], row[3], row[4], row[5]
        );
        rows.push(row);
    }
    let med = |i: usize| {
        let mut v: Vec<f64> = rows
            .iter()
            .map(|r| r[i])
            .filter(|x| x.is_finite())
            .collect();
        v.sort_by(f64::total_cmp);
        (
            v.get(v.len() / 2).copied().unwrap_or(f64::NAN),
            v.iter().sum::<f64>() / v.len().max(1) as f64,
        )
    };
    let (mr, ar) = med(2);
    let (mb, ab) = med(3);
    println!("NEES (6 = consistent): raw median {mr:.1} mean {ar:.1}; bilateral median {mb:.1} mean {ab:.1}");
    Ok(())
}
