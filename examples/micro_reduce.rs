use rgbid::geometry::Se3;
use rgbid::image::{ImageF32, RgbdFrame};
use rgbid::odometry::cpu::{self, CpuPyramid};
use rgbid::odometry::kernel::WarpParams;
use std::time::Instant;

fn frame(w: usize, h: usize, s: f32) -> RgbdFrame {
    let mut i = Vec::new();
    let mut r = Vec::new();
    for y in 0..h {
        for x in 0..w {
            let (fx, fy) = (x as f32 + s, y as f32);
            i.push(
                120.0
                    + 60.0 * (fx * 0.07).sin() * (fy * 0.05).cos()
                    + 20.0 * (fx * 0.31 + fy * 0.17).sin(),
            );
            r.push(0.5 + 0.0002 * fx + 0.0001 * fy);
        }
    }
    RgbdFrame {
        timestamp: 0.0,
        intensity: ImageF32::from_vec(w, h, i).unwrap(),
        inverse_depth: ImageF32::from_vec(w, h, r).unwrap(),
    }
}

fn main() {
    let (w, h) = (640usize, 480usize);
    let a = frame(w, h, 0.0);
    let b = frame(w, h, 1.5);
    let t = Instant::now();
    for _ in 0..10 {
        let _ = CpuPyramid::build(&a, 4);
    }
    println!("pyramid {:.2} ms", t.elapsed().as_secs_f64() * 100.0);
    let (pa, pb) = (CpuPyramid::build(&a, 4), CpuPyramid::build(&b, 4));
    let pose = Se3::exp(&[0.01, 0.0, 0.005, 0.001, 0.002, 0.0]);
    let mut off = 0u32;
    for level in 0..4 {
        let (lw, lh) = (w >> level, h >> level);
        let f = 525.0 / (1 << level) as f32;
        let mut p = WarpParams {
            dims: [lw as u32, lh as u32, off, 19200.min((lw * lh) as u32)],
            intr: [f, f, lw as f32 / 2.0, lh as f32 / 2.0],
            rot: [[0.0; 4]; 3],
            robust: [5.0, 0.002, 5.0, 5.0],
            flags: [3, 3, 0, 0],
        };
        off += (lw * lh) as u32;
        p.set_pose(&pose);
        let reps = 20;
        let t = Instant::now();
        let mut s = 0.0;
        for _ in 0..reps {
            let v = cpu::normal_equation_partials(&p, &pa, &pb, level, 16);
            s += v[0][0];
        }
        let ms = t.elapsed().as_secs_f64() * 1e3 / reps as f64;
        let t2 = Instant::now();
        for _ in 0..reps {
            let v = cpu::sample_residuals(&p, &pa, &pb, level);
            s += v[0][0];
        }
        let ms2 = t2.elapsed().as_secs_f64() * 1e3 / reps as f64;
        println!("level {level} {lw}x{lh}: reduce {ms:.3} ms = {:.1} ns/px wall; sample {ms2:.3} ms ({s:.1})", ms * 1e6 / (lw * lh) as f64);
    }
}
