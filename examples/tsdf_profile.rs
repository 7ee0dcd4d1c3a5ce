//! Times the TSDF integration on the CPU backend over a TUM-format folder with ground-truth
//! poses (for example the sequence `rgbid bench tsdf` writes), loading each frame just before
//! integrating it as the benchmark does, and prints, per repetition, the median milliseconds
//! per frame of the whole integration, its block allocation and its kernel, and a checksum of
//! the volume (vertex count of the extracted mesh).
//!
//! `cargo run --release --example tsdf_profile -- SEQ [REPS] [--no-colour]`
//!
//! For comparing two builds of the kernel, run their binaries alternately and compare the
//! fastest repetitions: one run's median moves by more than small kernel changes do.

use std::time::Instant;

use rgbid::gpu::ComputeBackend;
use rgbid::image::RgbdFrame;
use rgbid::io::trajectory::read_tum;
use rgbid::io::tum::{OpenOptions, TumSequence};
use rgbid::tsdf::{TsdfParams, TsdfVolume};

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    v.get(v.len() / 2).copied().unwrap_or(f64::NAN)
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let colour = !args.iter().any(|a| a == "--no-colour");
    let pos: Vec<&String> = args.iter().filter(|a| !a.starts_with("--")).collect();
    let folder = std::path::PathBuf::from(
        pos.first()
            .ok_or("usage: tsdf_profile SEQ [REPS] [--no-colour]")?,
    );
    let reps: usize = pos.get(1).map(|s| s.parse()).transpose()?.unwrap_or(3);
    let tum = TumSequence::open(&folder, &OpenOptions::default())?;
    let gt = read_tum(&folder.join("groundtruth.txt"))?;
    let cam = tum.undistorted_camera();
    let params = TsdfParams {
        voxel_size: 0.02,
        ..Default::default()
    };
    for _ in 0..reps {
        let mut vol = TsdfVolume::new(params, cam, &ComputeBackend::Cpu)?;
        let (mut total, mut alloc, mut kernel) = (Vec::new(), Vec::new(), Vec::new());
        for i in 0..tum.len() {
            let mut frame = tum.load(i)?;
            if !colour {
                let t = frame.timestamp();
                let (intensity, rho) = frame.into_images();
                frame = RgbdFrame::new(t, intensity, rho)?;
            }
            let pose = gt.get(i).ok_or("ground truth too short")?.world_from_camera;
            let t = Instant::now();
            let s = vol.integrate(&frame, &pose)?;
            total.push(t.elapsed().as_secs_f64() * 1e3);
            alloc.push(s.allocate_s * 1e3);
            kernel.push(s.kernel_s * 1e3);
        }
        let verts = vol.extract_mesh()?.vertices.len();
        println!(
            "total {:.3} alloc {:.3} kernel {:.3}  verts {verts}",
            median(&mut total),
            median(&mut alloc),
            median(&mut kernel)
        );
    }
    Ok(())
}
