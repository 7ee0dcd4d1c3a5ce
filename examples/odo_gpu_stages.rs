//! Per-stage host timings of the GPU odometry kernels (each call waited on, medians of
//! `reps` repetitions) on two frames of a TUM folder, to see where a lavapipe frame goes:
//! `cargo run --release --example odo_gpu_stages -- ../shared/data/rgbd/redkitchen_0_299 [reps]`.

use std::time::Instant;

use rgbid::geometry::Se3;
use rgbid::gpu::{select_backend, BackendChoice, ComputeBackend};
use rgbid::io::tum::{OpenOptions, TumSequence};
use rgbid::odometry::gpu::GpuOdometry;
use rgbid::odometry::kernel::WarpParams;
use rgbid::odometry::*;

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// CPU time of the whole process (all threads, llvmpipe's included), ms.
fn cpu_ms() -> f64 {
    let mut t = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: `t` is a valid timespec for the call to write.
    unsafe { libc::clock_gettime(libc::CLOCK_PROCESS_CPUTIME_ID, &mut t) };
    t.tv_sec as f64 * 1e3 + t.tv_nsec as f64 * 1e-6
}

/// Median wall time, ms; prints nothing. The median process CPU time (which other load on a
/// shared machine disturbs much less) goes to `CPU`.
fn time<F: FnMut()>(reps: usize, mut f: F) -> String {
    f();
    let (mut w, mut c) = (Vec::new(), Vec::new());
    for _ in 0..reps {
        let (t, c0) = (Instant::now(), cpu_ms());
        f();
        c.push(cpu_ms() - c0);
        w.push(t.elapsed().as_secs_f64() * 1e3);
    }
    format!("{:.2} ms (cpu {:.2})", median(w), median(c))
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let dir = args
        .get(1)
        .cloned()
        .unwrap_or("../shared/data/rgbd/redkitchen_0_299".into());
    let reps: usize = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(20);
    let seq = TumSequence::open(std::path::Path::new(&dir), &OpenOptions::default())?;
    let f0 = seq.load(0)?;
    let f1 = seq.load(1)?;
    let cam = seq.camera;
    let ComputeBackend::Gpu(ctx) = select_backend(BackendChoice::Gpu, None)? else {
        return Err("no gpu".into());
    };
    let cfg = OdometryConfig::default();
    let subgroups = std::env::var("SUBGROUPS").map(|v| v != "0").unwrap_or(true);
    let mut g = GpuOdometry::with_reduction(ctx.clone(), subgroups)?;
    let levels = cfg.levels;
    let r = g.build(&f0, levels, None)?;
    let mut c = Some(g.build(&f1, levels, None)?);
    ctx.wait()?;
    println!(
        "adapter {} reps {reps} subgroups {subgroups}",
        ctx.info.name
    );
    let t = time(reps, || {
        let p = g.build(&f1, levels, c.take()).unwrap();
        ctx.wait().unwrap();
        c = Some(p);
    });
    println!("build (upload + pyramid + gradients, waited): {t}");
    let first = cfg.finest_level(cam.width as usize);
    let stored = first.min(cfg.covisibility_level);
    let t = time(reps, || {
        let p = g
            .build_levels(&f1, levels, stored, first, c.take())
            .unwrap();
        ctx.wait().unwrap();
        c = Some(p);
    });
    println!("build as the tracker does (levels from {stored}, gradients from {first}): {t}");
    for l in 1..levels {
        let mut spare = None;
        let t = time(reps, || {
            let p = g.build(&f1, l, spare.take()).unwrap();
            ctx.wait().unwrap();
            spare = Some(p);
        });
        println!("  build with {l} levels: {t}");
    }
    let up = ctx.storage("upload probe", (f1.width() * f1.height() * 8) as u64);
    let t = time(reps, || {
        ctx.queue
            .write_buffer(&up, 0, bytemuck::cast_slice(&f1.intensity.data));
        ctx.queue.submit([]);
        ctx.wait().unwrap();
    });
    println!("  upload of the intensity plane alone: {t}");
    let small = ctx.storage("probe", 64);
    let t = time(reps, || {
        let _: Vec<f32> = ctx.read_buffer(&small, 4).unwrap();
    });
    println!("empty round trip (copy 16 B + map, new staging): {t}");
    let c = c.take().unwrap();
    let pose = Se3::IDENTITY;
    for level in 0..levels {
        let lc = cam.at_level(level);
        let mut off = 0u32;
        let (mut lw, mut lh) = (cam.width, cam.height);
        for _ in 0..level {
            off += lw * lh;
            lw /= 2;
            lh /= 2;
        }
        let n = lc.width * lc.height;
        let mut p = WarpParams {
            dims: [lc.width, lc.height, off, n.min(cfg.max_samples as u32)],
            intr: [lc.fx as f32, lc.fy as f32, lc.cx as f32, lc.cy as f32],
            rot: [[0.0; 4]; 3],
            robust: [5.0, 0.0025, 5.0, 5.0],
            flags: [cfg.estimator.code(), cfg.terms.mask(), 0, 0],
        };
        p.set_pose(&pose);
        let ne = time(reps, || {
            g.normal_equation_partials(&p, &r, &c).unwrap();
        });
        let sa = time(reps, || {
            g.sample_residuals(&p, &r, &c).unwrap();
        });
        let both = time(reps, || {
            g.normal_equations_and_sample(&p, &r, &c).unwrap();
        });
        let cov = time(reps, || {
            g.covisibility_counts(&p, &r, &c).unwrap();
        });
        println!(
            "level {level} {}x{}: normal eq {ne}, sample {sa}, both {both}, covisibility {cov}",
            lc.width, lc.height
        );
        if level == 1 {
            let (_, s) = g.normal_equations_and_sample(&p, &r, &c)?;
            let pop = |k: usize| -> Vec<f64> {
                s.iter()
                    .filter(|v| v[k] != kernel::INVALID_RESIDUAL)
                    .map(|v| f64::from(v[k]))
                    .collect()
            };
            let (a, b) = (pop(0), pop(1));
            let est = time(reps, || {
                let _ = rayon::join(
                    || estimate_scale_full(&a, cfg.estimator, cfg.scale),
                    || estimate_scale_full(&b, cfg.estimator, cfg.scale),
                );
            });
            println!("  CPU full scale estimate on the level-1 sample: {est}");
        }
    }
    Ok(())
}

fn estimate_scale_full(r: &[f64], e: Estimator, m: ScaleMethod) -> robust::ScaleEstimate {
    robust::estimate_scale(r, e, m)
}
