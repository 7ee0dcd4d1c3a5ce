//! Per-stage timing of superjut segmentation on frames of a TUM-layout sequence (median ms):
//! `cargo run --release --example segment_stages -- SEQ [STEP]`.

use std::time::Instant;

use rgbid::io::tum::{OpenOptions, TumSequence};
use rgbid::segment::{self, graph, SegmentConfig};

fn main() -> anyhow::Result<()> {
    let mut args = std::env::args().skip(1);
    let dir = args
        .next()
        .ok_or_else(|| anyhow::anyhow!("usage: segment_stages SEQ [STEP]"))?;
    let step: usize = args.next().map_or(Ok(30), |s| s.parse())?;
    let seq = TumSequence::open(std::path::Path::new(&dir), &OpenOptions::default())?;
    let cam = seq.undistorted_camera();
    let cfg = SegmentConfig::default();
    let names = [
        "normals",
        "points",
        "edges",
        "sort",
        "felzenszwalb",
        "eigen-transform",
        "total",
    ];
    let mut t: Vec<Vec<f64>> = vec![Vec::new(); names.len()];
    for i in (0..seq.len()).step_by(step) {
        let f = seq.load(i)?;
        let (w, h) = (f.intensity.width, f.intensity.height);
        let t0 = Instant::now();
        let mut lap = |k: usize, s: &mut Instant| {
            t[k].push(s.elapsed().as_secs_f64() * 1e3);
            *s = Instant::now();
        };
        let mut s = Instant::now();
        let n = segment::normals_cpu(&f.inverse_depth, &cam, &cfg.normals);
        lap(0, &mut s);
        let p = segment::points_from_inverse_depth(&f.inverse_depth, &cam);
        lap(1, &mut s);
        let mut e = graph::image_edges(w, h, &p, &n.data, &f.inverse_depth.data, cfg.jump_ratio);
        lap(2, &mut s);
        graph::sort_edges(&mut e);
        lap(3, &mut s);
        let active: Vec<bool> = (0..w * h).map(|i| n.is_valid(i)).collect();
        let _ = graph::felzenszwalb(w * h, &e, cfg.k, cfg.min_size, &active);
        lap(4, &mut s);
        let _ = segment::features::eigen_transform_samples(
            &f.intensity,
            cfg.texture_window,
            cfg.texture_first,
            cfg.texture_stride,
        );
        lap(5, &mut s);
        let _ = t0;
        let s2 = Instant::now();
        let _ = segment::segment_keyframe(&f.intensity, &f.inverse_depth, &cam, &cfg)?;
        t[6].push(s2.elapsed().as_secs_f64() * 1e3);
    }
    for (name, mut v) in names.iter().zip(t) {
        v.sort_by(f64::total_cmp);
        println!("{name:>14}: {:7.2} ms", v[v.len() / 2]);
    }
    Ok(())
}
