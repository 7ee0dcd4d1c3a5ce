//! `rgbid vocab`: train, inspect and convert bag-of-binary-words vocabularies.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use indicatif::{ProgressBar, ProgressStyle};
use rand::{Rng, SeedableRng};
use rayon::prelude::*;
use rgbid::image::ImageF32;
use rgbid::place::{extract_orb, Descriptor, OrbParams, TrainParams, Vocabulary};

/// Subcommands of `rgbid vocab`.
#[derive(clap::Subcommand)]
pub enum Command {
    /// Train a vocabulary from images or TUM-layout sequences (their rgb/ folder), and/or
    /// from procedurally rendered images.
    Train(TrainArgs),
    /// Print a vocabulary's shape and weights.
    Info {
        /// Vocabulary file (rgbid binary or DBoW2 text).
        vocab: PathBuf,
    },
    /// Convert between the binary format and the DBoW2 text format (by output extension:
    /// `.txt` writes text, anything else binary).
    Convert {
        /// Input vocabulary.
        input: PathBuf,
        /// Output file.
        output: PathBuf,
    },
}

/// Arguments of `rgbid vocab train`.
#[derive(clap::Args)]
pub struct TrainArgs {
    /// Image files, folders of images, or TUM sequence folders.
    pub inputs: Vec<PathBuf>,
    /// Branching factor, >= 2.
    #[arg(long, value_parser = crate::cli::options::range::at_least_two, default_value_t = 10)]
    pub k: usize,
    /// Tree depth, >= 1.
    #[arg(long, value_parser = crate::cli::options::range::at_least_one, default_value_t = 5)]
    pub levels: usize,
    /// Output file (binary; `.txt` writes the DBoW2 text format).
    #[arg(long)]
    pub out: PathBuf,
    /// Use every N-th image of each folder (N >= 1).
    #[arg(long, value_parser = crate::cli::options::range::at_least_one, default_value_t = 1)]
    pub every: usize,
    /// ORB keypoints per image, >= 1.
    #[arg(long, value_parser = crate::cli::options::range::at_least_one, default_value_t = 1000)]
    pub features: usize,
    /// Also train on N procedurally rendered images (random textured shapes, rendered here) (a whole number >= 0).
    #[arg(long, value_parser = crate::cli::options::range::count, default_value_t = 0)]
    pub procedural: usize,
    /// Seed of the clustering and the procedural images (any whole number, 0 to 2^64-1).
    #[arg(long, value_parser = crate::cli::options::range::seed, default_value_t = 7)]
    pub seed: u64,
}

/// Runs the subcommand.
pub fn run(c: Command) -> Result<()> {
    match c {
        Command::Train(a) => train(a),
        Command::Info { vocab } => {
            let v = Vocabulary::load(&vocab)?;
            let ws: Vec<f64> = (0..v.num_words() as u32)
                .filter_map(|w| v.word_weight(w))
                .collect();
            let mean = ws.iter().sum::<f64>() / ws.len().max(1) as f64;
            println!(
                "k={} L={} nodes={} words={} weighting={:?} scoring={:?} mean weight {:.3}",
                v.k(),
                v.levels(),
                v.num_nodes(),
                v.num_words(),
                v.weighting(),
                v.scoring(),
                mean
            );
            Ok(())
        }
        Command::Convert { input, output } => {
            let v = Vocabulary::load(&input)?;
            save(&v, &output)
        }
    }
}

fn save(v: &Vocabulary, out: &Path) -> Result<()> {
    if out.extension().is_some_and(|e| e == "txt") {
        let f =
            std::fs::File::create(out).with_context(|| format!("creating {}", out.display()))?;
        v.write_dbow2_text(std::io::BufWriter::new(f))?;
    } else {
        v.save(out)?;
    }
    Ok(())
}

fn is_image(p: &Path) -> bool {
    p.extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| matches!(e.to_ascii_lowercase().as_str(), "png" | "jpg" | "jpeg"))
}

/// Image files of the inputs: files as given; folders' images (a TUM folder's rgb/), sorted.
fn collect_images(inputs: &[PathBuf], every: usize) -> Result<Vec<PathBuf>> {
    let mut out = Vec::new();
    for p in inputs {
        if p.is_file() {
            out.push(p.clone());
            continue;
        }
        let dir = if p.join("rgb").is_dir() {
            p.join("rgb")
        } else {
            p.clone()
        };
        let mut files: Vec<PathBuf> = std::fs::read_dir(&dir)
            .with_context(|| format!("reading {}", dir.display()))?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| is_image(p))
            .collect();
        files.sort();
        out.extend(files.into_iter().step_by(every.max(1)));
    }
    Ok(out)
}

/// A procedural training image: random rotated rectangles, discs and stripes over a smooth
/// gradient, 2x2 supersampled. Rendered entirely here, no external data.
pub fn procedural_image(w: usize, h: usize, seed: u64) -> ImageF32 {
    let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
    let n = rng.random_range(60..160);
    let shapes: Vec<(u8, [f64; 6], f32)> = (0..n)
        .map(|_| {
            let kind = rng.random_range(0..3u8);
            let p = [
                rng.random_range(0.0..w as f64),
                rng.random_range(0.0..h as f64),
                rng.random_range(3.0..45.0),
                rng.random_range(3.0..45.0),
                rng.random_range(0.0..std::f64::consts::PI),
                rng.random_range(2.0..10.0),
            ];
            (kind, p, rng.random_range(0.0..255.0))
        })
        .collect();
    let g = [
        rng.random_range(40.0..160.0),
        rng.random_range(-0.2..0.2),
        rng.random_range(-0.2..0.2),
    ];
    let value = |x: f64, y: f64| -> f32 {
        let mut v = (g[0] + g[1] * x + g[2] * y) as f32;
        for (kind, p, val) in &shapes {
            let (dx, dy) = (x - p[0], y - p[1]);
            let (s, c) = p[4].sin_cos();
            let (u, v2) = (c * dx + s * dy, -s * dx + c * dy);
            let inside = match kind {
                0 => u.abs() < p[2] && v2.abs() < p[3],
                1 => dx * dx + dy * dy < p[2] * p[2],
                _ => u.abs() < p[2] && v2.abs() < p[3] && ((v2 / p[5]).floor() as i64) % 2 == 0,
            };
            if inside {
                v = *val;
            }
        }
        v
    };
    let data: Vec<f32> = (0..w * h)
        .into_par_iter()
        .map(|i| {
            let (x, y) = ((i % w) as f64, (i / w) as f64);
            (value(x - 0.25, y - 0.25)
                + value(x + 0.25, y - 0.25)
                + value(x - 0.25, y + 0.25)
                + value(x + 0.25, y + 0.25))
                / 4.0
        })
        .collect();
    ImageF32::from_vec(w, h, data).unwrap_or_else(|| ImageF32::filled(w, h, 0.0))
}

fn train(a: TrainArgs) -> Result<()> {
    let files = collect_images(&a.inputs, a.every)?;
    if files.is_empty() && a.procedural == 0 {
        bail!("no training images: give image files / folders or --procedural N");
    }
    let orb = OrbParams {
        n_features: a.features,
        ..Default::default()
    };
    let n = files.len() + a.procedural;
    let pb = ProgressBar::new(n as u64);
    if let Ok(s) = ProgressStyle::with_template("ORB {bar:40} {pos}/{len} {elapsed}") {
        pb.set_style(s);
    }
    let mut sets: Vec<Vec<Descriptor>> = Vec::with_capacity(n);
    for f in &files {
        let img = super::place::load_intensity(f)?;
        sets.push(extract_orb(&img, None, &orb)?.descriptors);
        pb.inc(1);
    }
    for i in 0..a.procedural {
        let img = procedural_image(
            640,
            480,
            a.seed.wrapping_mul(1_000_003).wrapping_add(i as u64),
        );
        sets.push(extract_orb(&img, None, &orb)?.descriptors);
        pb.inc(1);
    }
    pb.finish_and_clear();
    let total: usize = sets.iter().map(Vec::len).sum();
    println!(
        "{} images, {} descriptors; clustering k={} L={}",
        sets.len(),
        total,
        a.k,
        a.levels
    );
    let t0 = std::time::Instant::now();
    let params = TrainParams {
        k: a.k,
        levels: a.levels,
        seed: a.seed,
        ..Default::default()
    };
    let v = Vocabulary::train(&sets, &params)?;
    println!(
        "{} words, {} nodes in {:.1} s",
        v.num_words(),
        v.num_nodes(),
        t0.elapsed().as_secs_f64()
    );
    save(&v, &a.out)?;
    println!("wrote {}", a.out.display());
    Ok(())
}
