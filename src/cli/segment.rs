//! `rgbid segment`: superjut segmentation of frames of a TUM-layout sequence.
//!
//! Writes per frame a colour-coded segment image, a neg-entropy image, one mask per
//! threshold, and one CSV (`superjuts.csv`) with the features of every superjut.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context, Result};
use rgbid::camera::PinholeCamera;
use rgbid::gpu::{select_backend, BackendChoice, ComputeBackend};
use rgbid::image::{rgb_to_intensity, ImageF32};
use rgbid::segment::{self, GpuNormals, SegmentConfig};

/// Arguments of `rgbid segment`.
#[derive(clap::Args)]
pub struct Args {
    /// Sequence folder in TUM layout (`associations.txt` or `rgb.txt` + `depth.txt`,
    /// optional `calib.txt` with `fx fy cx cy depth_factor`).
    pub seq: PathBuf,
    /// Frames to segment: a comma-separated list of indices and ranges `a..b` or `a..b:step`
    /// (end exclusive), e.g. `0,10,20..100:20`.
    #[arg(long, default_value = "0")]
    pub frames: String,
    /// Output folder (created if missing).
    #[arg(long)]
    pub out: PathBuf,
    /// Neg-entropy thresholds of the masks.
    #[arg(long, value_delimiter = ',', default_value = "0.3,0.5,0.7")]
    pub thresholds: Vec<f64>,
    /// Felzenszwalb-Huttenlocher scale k.
    #[arg(long, default_value_t = 0.6)]
    pub k: f32,
    /// Minimum superjut size in pixels.
    #[arg(long, default_value_t = 200)]
    pub min_size: usize,
    /// Finite-difference step of the normals, pixels.
    #[arg(long, default_value_t = 2)]
    pub normal_step: u32,
    /// Up direction in the camera frame for horizontality, `x,y,z` (normalised).
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "0,-1,0",
        allow_hyphen_values = true
    )]
    pub up: Vec<f32>,
    /// Where the normal kernel runs.
    #[arg(long, value_enum, default_value_t = BackendChoice::Cpu)]
    pub backend: BackendChoice,
    /// Intrinsics `fx,fy,cx,cy` overriding `calib.txt` (default without either: TUM 525,525,319.5,239.5).
    #[arg(long, value_delimiter = ',')]
    pub intrinsics: Option<Vec<f64>>,
    /// Depth PNG units per metre overriding `calib.txt` (TUM: 5000).
    #[arg(long)]
    pub depth_factor: Option<f64>,
}

fn parse_frames(spec: &str) -> Result<Vec<usize>> {
    let mut out = Vec::new();
    for part in spec.split(',').map(str::trim).filter(|s| !s.is_empty()) {
        if let Some((a, rest)) = part.split_once("..") {
            let (b, step) = match rest.split_once(':') {
                Some((b, s)) => (
                    b,
                    s.parse::<usize>()
                        .with_context(|| format!("bad step in '{part}'"))?,
                ),
                None => (rest, 1),
            };
            let a: usize = a
                .parse()
                .with_context(|| format!("bad range start in '{part}'"))?;
            let b: usize = b
                .parse()
                .with_context(|| format!("bad range end in '{part}'"))?;
            if step == 0 {
                bail!("step 0 in '{part}'");
            }
            out.extend((a..b).step_by(step));
        } else {
            out.push(
                part.parse()
                    .with_context(|| format!("bad frame index '{part}'"))?,
            );
        }
    }
    Ok(out)
}

/// (timestamp, rgb path, depth path) per frame.
fn read_list(seq: &Path) -> Result<Vec<(f64, PathBuf, PathBuf)>> {
    let assoc = seq.join("associations.txt");
    let lines = |p: &Path| -> Result<Vec<Vec<String>>> {
        let text =
            std::fs::read_to_string(p).with_context(|| format!("reading {}", p.display()))?;
        Ok(text
            .lines()
            .map(str::trim)
            .filter(|l| !l.is_empty() && !l.starts_with('#'))
            .map(|l| l.split_whitespace().map(String::from).collect())
            .collect())
    };
    if assoc.exists() {
        let mut out = Vec::new();
        for (n, f) in lines(&assoc)?.into_iter().enumerate() {
            if f.len() < 4 {
                bail!(
                    "{}: line {} has {} fields, expected 4",
                    assoc.display(),
                    n + 1,
                    f.len()
                );
            }
            let t: f64 = f[0]
                .parse()
                .with_context(|| format!("{}: bad timestamp '{}'", assoc.display(), f[0]))?;
            out.push((t, seq.join(&f[1]), seq.join(&f[3])));
        }
        return Ok(out);
    }
    let parse = |p: &Path| -> Result<Vec<(f64, String)>> {
        lines(p)?
            .into_iter()
            .map(|f| {
                if f.len() < 2 {
                    bail!("{}: line with fewer than 2 fields", p.display());
                }
                Ok((
                    f[0].parse::<f64>()
                        .with_context(|| format!("{}: bad timestamp", p.display()))?,
                    f[1].clone(),
                ))
            })
            .collect()
    };
    let rgb = parse(&seq.join("rgb.txt"))?;
    let depth = parse(&seq.join("depth.txt"))?;
    if depth.is_empty() {
        bail!("{}: no depth images", seq.display());
    }
    Ok(rgb
        .into_iter()
        .map(|(t, r)| {
            let d = depth
                .iter()
                .min_by(|a, b| (a.0 - t).abs().total_cmp(&(b.0 - t).abs()))
                .map(|d| d.1.clone())
                .unwrap_or_default();
            (t, seq.join(r), seq.join(d))
        })
        .collect())
}

fn load_frame(rgb: &Path, depth: &Path, depth_factor: f64) -> Result<(ImageF32, ImageF32)> {
    let c = image::open(rgb)
        .with_context(|| format!("reading {}", rgb.display()))?
        .to_rgb8();
    let d = image::open(depth)
        .with_context(|| format!("reading {}", depth.display()))?
        .to_luma16();
    if c.dimensions() != d.dimensions() {
        bail!("{} and {} differ in size", rgb.display(), depth.display());
    }
    let (w, h) = (c.width() as usize, c.height() as usize);
    let intensity = c
        .pixels()
        .map(|p| rgb_to_intensity(p[0], p[1], p[2]))
        .collect();
    let inv = d
        .pixels()
        .map(|p| {
            if p[0] == 0 {
                0.0
            } else {
                (depth_factor / f64::from(p[0])) as f32
            }
        })
        .collect();
    Ok((
        ImageF32 {
            width: w,
            height: h,
            data: intensity,
        },
        ImageF32 {
            width: w,
            height: h,
            data: inv,
        },
    ))
}

fn save_gray(path: &Path, w: usize, h: usize, data: Vec<u8>) -> Result<()> {
    image::GrayImage::from_raw(w as u32, h as u32, data)
        .context("image buffer size")?
        .save(path)
        .with_context(|| format!("writing {}", path.display()))
}

/// Runs the subcommand.
pub fn run(args: Args) -> Result<()> {
    let list = read_list(&args.seq)?;
    let frames = parse_frames(&args.frames)?;
    if frames.is_empty() {
        bail!("--frames selects no frame");
    }
    if let Some(&bad) = frames.iter().find(|&&f| f >= list.len()) {
        bail!(
            "frame {bad} out of range: the sequence has {} frames",
            list.len()
        );
    }
    let calib: Option<Vec<f64>> = std::fs::read_to_string(args.seq.join("calib.txt"))
        .ok()
        .map(|t| {
            t.split_whitespace()
                .filter_map(|v| v.parse().ok())
                .collect()
        });
    let (k4, factor) = match (&args.intrinsics, &calib) {
        (Some(k), _) if k.len() == 4 => ([k[0], k[1], k[2], k[3]], None),
        (Some(_), _) => bail!("--intrinsics needs 4 values fx,fy,cx,cy"),
        (None, Some(c)) if c.len() >= 4 => ([c[0], c[1], c[2], c[3]], c.get(4).copied()),
        _ => {
            log::warn!("no calib.txt and no --intrinsics: using TUM defaults 525,525,319.5,239.5");
            ([525.0, 525.0, 319.5, 239.5], None)
        }
    };
    let depth_factor = args.depth_factor.or(factor).unwrap_or(5000.0);
    if args.up.len() != 3 {
        bail!("--up needs 3 values");
    }
    let ul = args.up.iter().map(|v| v * v).sum::<f32>().sqrt();
    if !(ul > 0.0) {
        bail!("--up must be non-zero");
    }
    let mut cfg = SegmentConfig {
        k: args.k,
        min_size: args.min_size,
        ..SegmentConfig::default()
    };
    cfg.normals.step = args.normal_step;
    cfg.up = [args.up[0] / ul, args.up[1] / ul, args.up[2] / ul];
    cfg.validate()?;
    let backend = select_backend(args.backend, None)?;
    log::info!("normals on {}", backend.name());
    let gpu = match &backend {
        ComputeBackend::Gpu(ctx) => Some(GpuNormals::new(ctx.clone())?),
        ComputeBackend::Cpu => None,
    };
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    let csv_path = args.out.join("superjuts.csv");
    let mut csv = std::io::BufWriter::new(
        std::fs::File::create(&csv_path)
            .with_context(|| format!("creating {}", csv_path.display()))?,
    );
    writeln!(
        csv,
        "frame,timestamp,label,size,entropy,neg_entropy,planarity,horizontality,texture,texture_samples,centroid_x,centroid_y,centroid_z,normal_x,normal_y,normal_z"
    )?;
    let bar = indicatif::ProgressBar::new(frames.len() as u64);
    let mut times = Vec::new();
    for &f in &frames {
        let (t, rgb, depth) = &list[f];
        let (intensity, inv) = load_frame(rgb, depth, depth_factor)?;
        let cam = PinholeCamera::new(
            k4[0],
            k4[1],
            k4[2],
            k4[3],
            inv.width as u32,
            inv.height as u32,
        );
        let t0 = Instant::now();
        let juts = match &gpu {
            Some(g) => {
                let n = g.compute(&inv, &cam, &cfg.normals)?;
                segment::segment_with_normals(&intensity, &inv, &cam, n, &cfg)?
            }
            None => segment::segment_keyframe(&intensity, &inv, &cam, &cfg)?,
        };
        times.push(t0.elapsed().as_secs_f64() * 1e3);
        let (w, h) = (juts.width, juts.height);
        let stem = format!("frame_{f:05}");
        image::RgbImage::from_raw(w as u32, h as u32, juts.colour_image())
            .context("image buffer size")?
            .save(args.out.join(format!("{stem}_segments.png")))?;
        let ne = juts
            .neg_entropy_image()
            .data
            .iter()
            .map(|v| {
                if v.is_nan() {
                    0
                } else {
                    (v * 255.0).round() as u8
                }
            })
            .collect();
        save_gray(&args.out.join(format!("{stem}_negentropy.png")), w, h, ne)?;
        for &th in &args.thresholds {
            let m = juts.mask(th);
            save_gray(
                &args.out.join(format!("{stem}_mask_{th:.2}.png")),
                w,
                h,
                m.data,
            )?;
        }
        for s in &juts.segments {
            writeln!(
                csv,
                "{f},{t:.6},{},{},{:.5},{:.5},{:.5},{:.5},{:.4},{},{:.4},{:.4},{:.4},{:.4},{:.4},{:.4}",
                s.label,
                s.size,
                s.entropy,
                s.neg_entropy,
                s.planarity,
                s.horizontality,
                s.texture,
                s.texture_samples,
                s.centroid[0],
                s.centroid[1],
                s.centroid[2],
                s.plane_normal[0],
                s.plane_normal[1],
                s.plane_normal[2]
            )?;
        }
        bar.inc(1);
    }
    bar.finish_and_clear();
    csv.flush()?;
    times.sort_by(f64::total_cmp);
    println!(
        "segmented {} frames into {}: median {:.1} ms per frame (normals + segmentation + features, {})",
        frames.len(),
        args.out.display(),
        times[times.len() / 2],
        backend.name()
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::parse_frames;

    #[test]
    fn frame_specs() {
        assert_eq!(
            parse_frames("0,3,10..16:2").unwrap(),
            vec![0, 3, 10, 12, 14]
        );
        assert!(parse_frames("1..5:0").is_err());
        assert!(parse_frames("x").is_err());
    }
}
