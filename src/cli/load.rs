//! `rgbid bench load`: SLAM under load. A long generated run (memory sampled as it goes:
//! bytes per keyframe, and whether the process grows per frame beyond what the map holds),
//! and two sessions on two threads of one process against the same two run one after the
//! other.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result};
use indicatif::{ProgressBar, ProgressStyle};
use rgbid::gpu::ComputeBackend;
use rgbid::place::Vocabulary;
use rgbid::slam::{Slam, SlamConfig};
use rgbid::source::{FrameSource, SynthOptions};
use rgbid::trajectory::TimedPose;

use super::options::range;

/// Arguments of `rgbid bench load` (CPU backend; generated `office:loop` frames).
#[derive(clap::Args)]
pub struct LoadBench {
    /// Frames of the long run, at 30 per second, one lap of the loop every 300 frames (>= 2).
    #[arg(long, value_parser = range::at_least_two, default_value_t = 20_000)]
    pub frames: usize,
    /// Image width in pixels (the height is 3/4 of it), 16 to 16384.
    #[arg(long, value_parser = range::image_side, default_value_t = 320)]
    pub width: u32,
    /// Frames between two memory samples (>= 1).
    #[arg(long, value_parser = range::at_least_one, default_value_t = 500)]
    pub sample_every: usize,
    /// Frames of each of the two sessions of the thread check (>= 2).
    #[arg(long, value_parser = range::at_least_two, default_value_t = 300)]
    pub session_frames: usize,
    /// Also write the results as JSON (machine, commit, command, samples) to this file, e.g.
    /// `docs/results/load.json` for `scripts/results.py`.
    #[arg(long, value_name = "FILE")]
    pub json: Option<PathBuf>,
}

/// One memory sample of the long run.
#[derive(serde::Serialize)]
struct Sample {
    /// Frames processed.
    frame: usize,
    /// Keyframes in the map.
    keyframes: usize,
    /// Resident memory of the process, bytes (VmRSS).
    rss_bytes: Option<u64>,
    /// Live heap of the process (allocated and not freed), bytes: see [`super::heap`].
    heap_bytes: usize,
    /// What the SLAM instance holds by its own account, bytes.
    instance_bytes: usize,
}

/// The two-thread check's figures.
#[derive(serde::Serialize)]
struct Threads {
    /// Frames of each session.
    frames: usize,
    /// Wall time of the two sessions one after the other, seconds.
    sequential_s: f64,
    /// Wall time of the two on two threads, seconds.
    parallel_s: f64,
    /// Poses per session (sequential, then parallel).
    poses: [[usize; 2]; 2],
    /// Largest distance between a pose of a parallel session and the same pose of its
    /// sequential run, metres.
    max_difference_m: f64,
}

/// Resident memory of this process, bytes (Linux; `None` elsewhere).
fn rss_bytes() -> Option<u64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = s.lines().find(|l| l.starts_with("VmRSS:"))?;
    let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb * 1024)
}

/// Least-squares slope of `y` over `x` (NaN with fewer than two distinct `x`).
fn slope(points: &[(f64, f64)]) -> f64 {
    let n = points.len() as f64;
    let mx = points.iter().map(|p| p.0).sum::<f64>() / n;
    let my = points.iter().map(|p| p.1).sum::<f64>() / n;
    let sxx: f64 = points.iter().map(|p| (p.0 - mx).powi(2)).sum();
    let sxy: f64 = points.iter().map(|p| (p.0 - mx) * (p.1 - my)).sum();
    if sxx > 0.0 {
        sxy / sxx
    } else {
        f64::NAN
    }
}

/// The generated source of `frames` frames of `office:loop`, session `session`.
fn source(frames: usize, width: u32, session: u32) -> Result<FrameSource> {
    let opts = SynthOptions {
        frames,
        width,
        laps: (frames as f64 / 300.0).max(1.0),
        ..SynthOptions::default()
    };
    let spec = opts.spec_of(SynthOptions::DEFAULT_SPEC, session, None)?;
    Ok(FrameSource::open(&spec, &ComputeBackend::Cpu)?)
}

/// Runs one session to the end; returns its trajectory.
fn session(frames: usize, width: u32, session_id: u32) -> Result<Vec<TimedPose>> {
    let mut src = source(frames, width, session_id)?;
    let mut slam = Slam::new(
        SlamConfig::default(),
        src.camera(),
        &ComputeBackend::Cpu,
        Vocabulary::embedded_default()?,
        None,
    )?;
    for i in 0..src.len() {
        slam.process(&src.load(i)?)
            .with_context(|| format!("session {session_id}, frame {i}"))?;
    }
    Ok(slam.finish()?.trajectory)
}

/// Largest distance between poses of equal index (infinite when the lengths differ).
fn max_difference(a: &[TimedPose], b: &[TimedPose]) -> f64 {
    if a.len() != b.len() {
        return f64::INFINITY;
    }
    a.iter()
        .zip(b)
        .map(|(p, q)| (p.world_from_camera.translation - q.world_from_camera.translation).length())
        .fold(0.0, f64::max)
}

/// Runs `rgbid bench load`.
pub fn run(a: LoadBench) -> Result<()> {
    let mut src = source(a.frames, a.width, 0)?;
    let camera = src.camera();
    println!(
        "load: {} frames {}x{} (office:loop, CPU backend), memory every {} frames",
        a.frames, camera.width, camera.height, a.sample_every
    );
    let mut slam = Slam::new(
        SlamConfig::default(),
        camera,
        &ComputeBackend::Cpu,
        Vocabulary::embedded_default()?,
        None,
    )?;
    let bar = ProgressBar::new(src.len() as u64);
    bar.set_style(
        ProgressStyle::with_template("{bar:40} {pos}/{len} frames {per_sec} eta {eta} {msg}")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    let t0 = Instant::now();
    let mut samples = Vec::new();
    let mut keyframes = 0;
    for i in 0..src.len() {
        let r = slam
            .process(&src.load(i)?)
            .with_context(|| format!("frame {i}"))?;
        keyframes = r.keyframes;
        bar.inc(1);
        if (i + 1) % a.sample_every == 0 || i + 1 == src.len() {
            let s = Sample {
                frame: i + 1,
                keyframes,
                rss_bytes: rss_bytes(),
                heap_bytes: super::heap::live_bytes(),
                instance_bytes: slam.memory().now.total(),
            };
            let large = super::heap::large_classes()
                .into_iter()
                .map(|(size, bytes)| format!("{}M:{:.0}MB", size >> 20, bytes as f64 / 1e6))
                .collect::<Vec<_>>()
                .join(" ");
            bar.suspend(|| {
                println!(
                    "frame {}: heap {:.1} MB, instance {:.1} MB; allocations >= 1 MiB by size: {large}",
                    s.frame,
                    s.heap_bytes as f64 / 1e6,
                    s.instance_bytes as f64 / 1e6
                )
            });
            bar.set_message(format!(
                "kf {keyframes}, rss {:.0} MB",
                s.rss_bytes.unwrap_or(0) as f64 / 1e6
            ));
            samples.push(s);
            if let Some(path) = &a.json {
                // The curve so far, so that a long run stopped early still leaves it.
                let body = serde_json::json!({
                    "frames": a.frames,
                    "width": camera.width,
                    "height": camera.height,
                    "complete": false,
                    "wall_s": t0.elapsed().as_secs_f64(),
                    "keyframes": keyframes,
                    "samples": samples,
                });
                let meta = super::report::meta(Vec::new());
                bar.suspend(|| super::report::write(path, "load", &meta, &body))?;
            }
        }
    }
    bar.finish_and_clear();
    let result = slam.finish()?;
    let wall_s = t0.elapsed().as_secs_f64();
    println!("| frame | keyframes | rss MB | heap MB | instance MB |");
    println!("|---|---|---|---|---|");
    for s in &samples {
        println!(
            "| {} | {} | {} | {:.1} | {:.1} |",
            s.frame,
            s.keyframes,
            s.rss_bytes
                .map_or("?".into(), |b| format!("{:.1}", b as f64 / 1e6)),
            s.heap_bytes as f64 / 1e6,
            s.instance_bytes as f64 / 1e6
        );
    }
    // Bytes per keyframe: the slope of each account over the keyframe count. Growth per frame
    // beyond the map: the slope over frames of what the process holds besides the instance.
    let per_kf = |f: &dyn Fn(&Sample) -> Option<f64>| {
        slope(
            &samples
                .iter()
                .filter_map(|s| Some((s.keyframes as f64, f(s)?)))
                .collect::<Vec<_>>(),
        )
    };
    let rss_per_keyframe = per_kf(&|s| s.rss_bytes.map(|b| b as f64));
    let heap_per_keyframe = per_kf(&|s| Some(s.heap_bytes as f64));
    let instance_per_keyframe = per_kf(&|s| Some(s.instance_bytes as f64));
    // The heap the instance's account does not cover, and the process beyond the heap, per
    // frame over the second half of the run (after one-time reservations such as the
    // per-thread scratch of the pose graph's dense kernels).
    let second_half = |f: &dyn Fn(&Sample) -> Option<f64>| {
        slope(
            &samples
                .iter()
                .filter(|s| 2 * s.frame >= a.frames)
                .filter_map(|s| Some((s.frame as f64, f(s)?)))
                .collect::<Vec<_>>(),
        )
    };
    let unaccounted_per_frame =
        second_half(&|s| Some(s.heap_bytes as f64 - s.instance_bytes as f64));
    let beyond_heap_per_frame = second_half(&|s| Some(s.rss_bytes? as f64 - s.heap_bytes as f64));
    let other_per_frame = slope(
        &samples
            .iter()
            .filter_map(|s| {
                Some((
                    s.frame as f64,
                    s.rss_bytes? as f64 - s.instance_bytes as f64,
                ))
            })
            .collect::<Vec<_>>(),
    );
    let map_per_keyframe = result.map.bytes_per_keyframe();
    println!(
        "{} keyframes in {wall_s:.0} s; bytes per keyframe: process {rss_per_keyframe:.0}, \
         heap {heap_per_keyframe:.0}, instance {instance_per_keyframe:.0}, saved map \
         {map_per_keyframe:.0}; process memory besides the instance grows {other_per_frame:.1} \
         bytes per frame; over the second half, per frame: heap outside the instance's account \
         {unaccounted_per_frame:.1} bytes, process beyond the heap {beyond_heap_per_frame:.1} bytes",
        result.keyframes().len()
    );
    drop(result);

    let n = a.session_frames;
    let t = Instant::now();
    let sequential = [session(n, a.width, 0)?, session(n, a.width, 1)?];
    let sequential_s = t.elapsed().as_secs_f64();
    let t = Instant::now();
    let parallel = std::thread::scope(|scope| {
        let h: Vec<_> = (0..2u32)
            .map(|k| scope.spawn(move || session(n, a.width, k)))
            .collect();
        h.into_iter()
            .map(|h| {
                h.join()
                    .map_err(|_| anyhow::anyhow!("a session thread panicked"))?
            })
            .collect::<Result<Vec<_>>>()
    })?;
    let parallel_s = t.elapsed().as_secs_f64();
    let max_difference_m = sequential
        .iter()
        .zip(&parallel)
        .map(|(s, p)| max_difference(s, p))
        .fold(0.0, f64::max);
    let threads = Threads {
        frames: n,
        sequential_s,
        parallel_s,
        poses: [
            [sequential[0].len(), sequential[1].len()],
            [parallel[0].len(), parallel[1].len()],
        ],
        max_difference_m,
    };
    println!(
        "two sessions of {n} frames: one after the other {sequential_s:.1} s, on two threads \
         {parallel_s:.1} s; poses {:?} / {:?}; largest pose difference {max_difference_m:.3e} m",
        threads.poses[0], threads.poses[1]
    );
    if let Some(path) = &a.json {
        let body = serde_json::json!({
            "frames": a.frames,
            "width": camera.width,
            "height": camera.height,
            "complete": true,
            "wall_s": wall_s,
            "keyframes": keyframes,
            "samples": samples,
            "rss_bytes_per_keyframe": rss_per_keyframe,
            "heap_bytes_per_keyframe": heap_per_keyframe,
            "unaccounted_heap_bytes_per_frame_second_half": unaccounted_per_frame,
            "beyond_heap_bytes_per_frame_second_half": beyond_heap_per_frame,
            "instance_bytes_per_keyframe": instance_per_keyframe,
            "map_bytes_per_keyframe": map_per_keyframe,
            "other_bytes_per_frame": other_per_frame,
            "threads": threads,
        });
        super::report::write(path, "load", &super::report::meta(Vec::new()), &body)?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn slope_of_a_line_and_of_too_few_points() {
        let s = slope(&[(0.0, 1.0), (1.0, 3.0), (2.0, 5.0)]);
        assert!((s - 2.0).abs() < 1e-12);
        assert!(slope(&[(1.0, 1.0), (1.0, 2.0)]).is_nan());
    }
}
