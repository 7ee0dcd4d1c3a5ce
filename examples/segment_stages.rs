//! Per-stage timing of superjut segmentation on frames of a TUM-layout sequence (median ms):
//! `cargo run --release --example segment_stages -- SEQ [STEP] [--reps R] [--dump FILE]
//! [--back-to-back-only]`.
//!
//! With `--reps R` every frame is timed `R` times and each stage's fastest run counts (the
//! median is then over frames), which filters out other processes on a busy machine. The
//! `cpu ms` column is the CPU time of all threads (Linux), which load does not inflate: for
//! one thread it is the unloaded wall time, for two busy threads about twice it.
//! The stages are those of `segment::Segmenter::segment_keyframe`, run one after another
//! through the public API; `sum` is their total and `total` times `segment_keyframe` itself on
//! the same frame (it overlaps independent stages, so it can be below `sum`). `graph` is the
//! fused edges + sort + Felzenszwalb-Huttenlocher of `graph::segment_image_graph_with` that
//! `segment_keyframe` runs (with its own kept buffers, as the segmenter keeps its); the three
//! separate functions are timed above it (not in `sum`). One `Segmenter` serves every
//! `segment_keyframe` call of the process, as a SLAM back-end keeps one. `--dump FILE` writes,
//! per frame, a hash of the label image and every superjut's features (f64 values as exact
//! bit patterns), to compare two builds for identical results.
//!
//! `back to back` then segments the same frames again, each once per round (`R` rounds),
//! one `segment_keyframe` call after another as a SLAM back-end does, and reports the median
//! over all calls: unlike the best-of-`R` stage rows, it includes what one call leaves the
//! next (page faults of fresh allocations, cold caches). With `--back-to-back-only` the stage
//! rows are skipped, so the process runs nothing but `segment_keyframe` calls (what one call
//! leaves the next is then not mixed with what the stage rows' separate functions left).

use std::io::Write;
use std::time::Instant;

use rgbid::internals::{segment_features, segment_graph as graph};
use rgbid::io::tum::{OpenOptions, TumSequence};
use rgbid::segment::{self, SegmentConfig, Segmenter, SphereBins};

fn main() -> anyhow::Result<()> {
    let mut step = 30usize;
    let mut dir = None;
    let mut dump = None;
    let mut reps = 1usize;
    let mut only_calls = false;
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        if a == "--reps" {
            reps = args
                .next()
                .ok_or_else(|| anyhow::anyhow!("--reps needs a count"))?
                .parse()?;
        } else if a == "--back-to-back-only" {
            only_calls = true;
        } else if a == "--dump" {
            dump = Some(
                args.next()
                    .ok_or_else(|| anyhow::anyhow!("--dump needs a file"))?,
            );
        } else if dir.is_none() {
            dir = Some(a);
        } else {
            step = a.parse()?;
        }
    }
    let dir =
        dir.ok_or_else(|| anyhow::anyhow!("usage: segment_stages SEQ [STEP] [--dump FILE]"))?;
    let mut dump = match dump {
        Some(p) => Some(std::io::BufWriter::new(std::fs::File::create(p)?)),
        None => None,
    };
    let seq = TumSequence::open(std::path::Path::new(&dir), &OpenOptions::default())?;
    let cam = seq.undistorted_camera();
    let cfg = SegmentConfig::default();
    // Built once, as the segmenter keeps its bins for the next keyframe.
    let bins = SphereBins::golden(cfg.bins);
    let mut segmenter = Segmenter::new();
    let mut graph_scratch = graph::GraphScratch::new();
    let names = [
        "normals",
        "points",
        "edges",
        "sort",
        "felzenszwalb",
        "graph",
        "eigen-transform",
        "smoothing",
        "smooth normals",
        "features",
        "sum",
        "total",
    ];
    let mut t: Vec<Vec<f64>> = vec![Vec::new(); names.len()];
    let mut t_cpu: Vec<Vec<f64>> = vec![Vec::new(); names.len()];
    let mut frames = Vec::new();
    for i in (0..seq.len()).step_by(step) {
        let f = seq.load(i)?;
        if only_calls {
            frames.push(f);
            continue;
        }
        let (w, h) = (f.intensity().width(), f.intensity().height());
        let mut best = vec![f64::INFINITY; names.len()];
        let mut best_cpu = vec![f64::INFINITY; names.len()];
        let mut juts = None;
        for _ in 0..reps.max(1) {
            let mut cur = vec![0.0f64; names.len()];
            let mut cur_cpu = vec![0.0f64; names.len()];
            let mut cpu0 = cpu_ms();
            let mut lap = |k: usize, s: &mut Instant| {
                cur[k] = s.elapsed().as_secs_f64() * 1e3;
                let c = cpu_ms();
                cur_cpu[k] = c - cpu0;
                cpu0 = c;
                *s = Instant::now();
            };
            let mut s = Instant::now();
            let n = segment::normals_cpu(f.inverse_depth(), &cam, &cfg.normals);
            lap(0, &mut s);
            let p = segment::points_from_inverse_depth(f.inverse_depth(), &cam);
            lap(1, &mut s);
            let mut e =
                graph::image_edges(w, h, &p, &n.data, f.inverse_depth().data(), cfg.jump_ratio);
            lap(2, &mut s);
            graph::sort_edges(&mut e);
            lap(3, &mut s);
            let active: Vec<bool> = (0..w * h).map(|i| n.is_valid(i)).collect();
            let (labels, count) = graph::felzenszwalb(w * h, &e, cfg.k, cfg.min_size, &active);
            lap(4, &mut s);
            drop(e);
            let fused = graph::segment_image_graph_with(
                &mut graph_scratch,
                w,
                h,
                &p,
                &n.data,
                f.inverse_depth().data(),
                cfg.jump_ratio,
                cfg.k,
                cfg.min_size,
                &active,
            );
            anyhow::ensure!(fused == (labels.clone(), count), "fused graph differs");
            lap(5, &mut s);
            let texture: Vec<(usize, f32)> = segment_features::eigen_transform_samples(
                f.intensity(),
                cfg.texture_window,
                cfg.texture_first,
                cfg.texture_stride,
            )
            .into_iter()
            .map(|(x, y, r)| (y as usize * w + x as usize, r))
            .collect();
            lap(6, &mut s);
            let smooth =
                segment::smooth_inverse_depth(f.inverse_depth(), &cfg.normals, Some(&labels));
            lap(7, &mut s);
            let feature_normals = smooth.map(|sm| {
                let mut data = segment::normals_cpu(&sm, &cam, &cfg.normals).data;
                for (i, v) in data.iter_mut().enumerate() {
                    if *v == [0.0; 3] {
                        *v = n.data[i];
                    }
                }
                data
            });
            lap(8, &mut s);
            let _ = segment_features::superjut_features(
                &labels,
                feature_normals.as_deref().unwrap_or(&n.data),
                &p,
                count,
                &bins,
                cfg.up,
                &texture,
            );
            lap(9, &mut s);
            cur[10] = [0, 1, 5, 6, 7, 8, 9].iter().map(|&k| cur[k]).sum();
            cur_cpu[10] = [0, 1, 5, 6, 7, 8, 9].iter().map(|&k| cur_cpu[k]).sum();
            let c2 = cpu_ms();
            let s2 = Instant::now();
            juts =
                Some(segmenter.segment_keyframe(f.intensity(), f.inverse_depth(), &cam, &cfg)?);
            cur[11] = s2.elapsed().as_secs_f64() * 1e3;
            cur_cpu[11] = cpu_ms() - c2;
            for (b, c) in best.iter_mut().zip(&cur) {
                *b = b.min(*c);
            }
            for (b, c) in best_cpu.iter_mut().zip(&cur_cpu) {
                *b = b.min(*c);
            }
        }
        for (v, b) in t.iter_mut().zip(&best) {
            v.push(*b);
        }
        for (v, b) in t_cpu.iter_mut().zip(&best_cpu) {
            v.push(*b);
        }
        frames.push(f);
        if let (Some(out), Some(juts)) = (dump.as_mut(), juts) {
            let mut hash = 0xcbf2_9ce4_8422_2325u64;
            for &l in &juts.labels {
                hash = (hash ^ u64::from(l)).wrapping_mul(0x0000_0100_0000_01b3);
            }
            writeln!(
                out,
                "frame {i} labels {hash:016x} segments {}",
                juts.segments.len()
            )?;
            for sj in &juts.segments {
                let bits = |v: f64| format!("{:016x}", v.to_bits());
                writeln!(
                    out,
                    "  {} size {} tex_n {} hist {:?} ent {} neg {} plan {} horiz {} tex {} c {} {} {} pn {} {} {}",
                    sj.label,
                    sj.size,
                    sj.texture_samples,
                    sj.histogram,
                    bits(sj.entropy),
                    bits(sj.neg_entropy),
                    bits(sj.planarity),
                    bits(sj.horizontality),
                    bits(sj.texture),
                    bits(sj.centroid[0]),
                    bits(sj.centroid[1]),
                    bits(sj.centroid[2]),
                    bits(sj.plane_normal[0]),
                    bits(sj.plane_normal[1]),
                    bits(sj.plane_normal[2]),
                )?;
            }
        }
    }
    let median = |mut v: Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    println!("{:>15}  {:>9}  {:>9}", "stage", "wall ms", "cpu ms");
    if !only_calls {
        for ((name, v), c) in names.iter().zip(t).zip(t_cpu) {
            println!("{name:>15}: {:9.2}  {:9.2}", median(v), median(c));
        }
    }
    let (mut wall, mut cpu) = (Vec::new(), Vec::new());
    for _ in 0..reps.max(1) {
        for f in &frames {
            let (c0, s0) = (cpu_ms(), Instant::now());
            let juts = segmenter.segment_keyframe(f.intensity(), f.inverse_depth(), &cam, &cfg)?;
            wall.push(s0.elapsed().as_secs_f64() * 1e3);
            cpu.push(cpu_ms() - c0);
            drop(juts);
        }
    }
    println!(
        "{:>15}: {:9.2}  {:9.2}  ({} calls)",
        "back to back",
        median(wall),
        median(cpu),
        frames.len() * reps.max(1)
    );
    Ok(())
}

/// CPU time (ms) this process's threads have run so far, from Linux's
/// `/proc/self/task/*/schedstat` (nanoseconds on a CPU); 0 elsewhere. Unlike wall time it does
/// not grow while other processes hold the cores.
fn cpu_ms() -> f64 {
    let Ok(tasks) = std::fs::read_dir("/proc/self/task") else {
        return 0.0;
    };
    tasks
        .flatten()
        .filter_map(|t| std::fs::read_to_string(t.path().join("schedstat")).ok())
        .filter_map(|s| s.split_whitespace().next()?.parse::<f64>().ok())
        .sum::<f64>()
        * 1e-6
}
