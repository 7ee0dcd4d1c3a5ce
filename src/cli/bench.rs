//! `rgbid bench`: speed benchmarks that print medians per frame and per stage (and, for real
//! sequences, the peers' figures measured in the same run).

use std::time::Instant;

use anyhow::Result;
use rgbid::camera::PinholeCamera;
use rgbid::geometry::Se3;
use rgbid::gpu::{select_backend, BackendChoice, ComputeBackend};
use rgbid::image::test_pattern;
use rgbid::odometry::{Odometry, OdometryConfig};

/// Subcommands of `rgbid bench`.
#[derive(clap::Subcommand)]
pub enum Command {
    /// Odometry kernels on generated frames (no data needed): pyramid, scale estimation,
    /// normal equations, solve, per backend and image size.
    Kernels(KernelBench),
}

/// Arguments of `rgbid bench kernels`.
#[derive(clap::Args)]
pub struct KernelBench {
    /// Backends to measure, comma-separated: cpu, gpu.
    #[arg(long, default_value = "cpu,gpu")]
    pub backends: String,
    /// Image sizes, comma-separated WxH.
    #[arg(long, default_value = "640x480,320x240")]
    pub sizes: String,
    /// Repetitions (the median is reported).
    #[arg(long, default_value_t = 15)]
    pub repeat: usize,
    /// GPU adapter name filter.
    #[arg(long)]
    pub adapter: Option<String>,
}

/// Median of a sample (NaN when empty).
pub fn median(v: &mut [f64]) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Runs the subcommand.
pub fn run(c: Command) -> Result<()> {
    match c {
        Command::Kernels(a) => kernels(a),
    }
}

fn backend_named(name: &str, adapter: Option<&str>) -> Result<Option<ComputeBackend>> {
    Ok(match name {
        "cpu" => Some(ComputeBackend::Cpu),
        "gpu" => match select_backend(BackendChoice::Gpu, adapter) {
            Ok(b) => Some(b),
            Err(e) => {
                println!("backend gpu: unavailable ({e})");
                None
            }
        },
        other => anyhow::bail!("unknown backend '{other}' (cpu or gpu)"),
    })
}

fn kernels(a: KernelBench) -> Result<()> {
    println!("| backend | size | align ms (median) | pyramid ms | scale ms | reduce ms | solve ms | GN iterations |");
    println!("|---|---|---|---|---|---|---|---|");
    for name in a
        .backends
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
    {
        let Some(backend) = backend_named(name, a.adapter.as_deref())? else {
            continue;
        };
        for size in a.sizes.split(',') {
            let (w, h) = size
                .split_once('x')
                .and_then(|(w, h)| {
                    Some((w.trim().parse::<u32>().ok()?, h.trim().parse::<u32>().ok()?))
                })
                .ok_or_else(|| anyhow::anyhow!("bad size '{size}' (expected WxH)"))?;
            let f = 525.0 * f64::from(w) / 640.0;
            let cam = PinholeCamera::new(
                f,
                f,
                (f64::from(w) - 1.0) / 2.0,
                (f64::from(h) - 1.0) / 2.0,
                w,
                h,
            );
            let frame_a = test_pattern(w as usize, h as usize, 1);
            let frame_b = test_pattern(w as usize, h as usize, 1);
            let mut odo = Odometry::new(OdometryConfig::default(), cam, &backend)?;
            let guess = Se3::exp(&[0.01, 0.0, 0.0, 0.0, 0.005, 0.0]);
            let mut totals = Vec::new();
            let mut stages: [Vec<f64>; 4] = Default::default();
            let mut iterations = 0;
            // One warm-up run (pipeline compilation on first dispatch), then the measured ones.
            odo.align(&frame_a, &frame_b, guess)?;
            for _ in 0..a.repeat.max(1) {
                let t = Instant::now();
                let r = odo.align(&frame_a, &frame_b, guess)?;
                totals.push(t.elapsed().as_secs_f64() * 1e3);
                let s = r.times;
                for (k, v) in [s.pyramid_ms, s.scale_ms, s.reduce_ms, s.solve_ms]
                    .into_iter()
                    .enumerate()
                {
                    stages[k].push(v);
                }
                iterations = r.levels.iter().map(|l| l.iterations).sum();
            }
            println!(
                "| {} | {w}x{h} | {:.2} | {:.2} | {:.2} | {:.2} | {:.3} | {iterations} |",
                backend.name(),
                median(&mut totals),
                median(&mut stages[0]),
                median(&mut stages[1]),
                median(&mut stages[2]),
                median(&mut stages[3])
            );
        }
    }
    println!("(align = pyramids of both frames + coarse-to-fine Gauss-Newton; the pyramid column is for both frames)");
    Ok(())
}
