//! `rgbid place`: loop detection over a TUM-layout sequence, and an ORB speed benchmark.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result};
use indicatif::{ProgressBar, ProgressStyle};
use rgbid::geometry::Se3;
use rgbid::image::{rgb_to_intensity, ImageF32};
use rgbid::io::tum::{OpenOptions, TumSequence};
use rgbid::io::CalibFormat;
use rgbid::place::{
    extract_orb, DetectedLoop, LoopDetector, LoopDetectorParams, OrbParams, Vocabulary,
};

use super::options::ConfigArgs;

/// Subcommands of `rgbid place`.
#[derive(clap::Subcommand)]
pub enum Command {
    /// Detect loops in a TUM-layout sequence (associations.txt, rgb/, depth/): lists each
    /// verified loop with its scores, inliers and relative pose.
    Loops(LoopsArgs),
    /// Time ORB extraction (and BoW conversion) on one image; prints ms per image.
    Bench(BenchArgs),
}

/// Arguments of `rgbid place loops`.
#[derive(clap::Args)]
pub struct LoopsArgs {
    /// Sequence folder (TUM layout).
    pub seq: PathBuf,
    /// Vocabulary file (rgbid binary or DBoW2 text, e.g. ORBvoc.txt); default: the embedded one.
    #[arg(long)]
    pub vocab: Option<PathBuf>,
    /// Ground truth (TUM trajectory, world_from_camera) for precision / recall.
    #[arg(long)]
    pub gt: Option<PathBuf>,
    /// Use every N-th frame as a keyframe (N >= 1).
    #[arg(long, value_parser = crate::cli::options::range::at_least_one, default_value_t = 1)]
    pub every: usize,
    /// Minimum separation between loop keyframes, in keyframes (`query.min_separation`)
    /// [default: 30]; a whole number >= 0.
    #[arg(long, value_parser = crate::cli::options::range::count)]
    pub min_separation: Option<usize>,
    /// Minimum normalised score of a candidate, in [0, 1] (`query.min_normalised_score`)
    /// [default: 0.3].
    #[arg(long, value_parser = crate::cli::options::range::unit)]
    pub min_score: Option<f64>,
    /// Configuration: a `LoopDetectorParams` file (`rgbid config dump --command place`; this
    /// command starts from `query.min_separation = 30` and a `direct_index_depth` of the
    /// vocabulary's depth less 3).
    #[command(flatten)]
    pub config: ConfigArgs,
    /// Camera: a preset (tum_fr1, tum_fr2, tum_fr3, default) or a camera config file (with
    /// the depth factor). Default: calib.txt beside the sequence, else the `default` preset.
    #[arg(long)]
    pub camera: Option<String>,
    /// How --camera FILE is read: `auto` (by the file: `calib.txt` is rgbid's `fx fy cx cy
    /// [depth_factor [width height]]`, `.yaml`/`.yml` OpenCV / ORB-SLAM, else `key = value`
    /// lines) or `droid` (DROID-SLAM's calib.txt: one line `fx fy cx cy [k1 k2 p1 p2 [k3]]`,
    /// pixels; the image size is taken from the sequence's first image, the depth factor is
    /// the layout's: TUM and ETH3D 5000 per metre, 7-Scenes and ScanNet 1000, Replica
    /// 6553.5).
    #[arg(long, value_enum, default_value_t = CalibFormat::Auto, requires = "camera")]
    pub calib_format: CalibFormat,
    /// Ground-truth revisit: camera centres closer than this (metres, > 0)...
    #[arg(long, value_parser = crate::cli::options::range::positive, default_value_t = 0.5)]
    pub gt_distance: f64,
    /// ...and optical axes closer than this (degrees, > 0).
    #[arg(long, value_parser = crate::cli::options::range::positive, default_value_t = 30.0)]
    pub gt_angle: f64,
}

/// Arguments of `rgbid place bench`.
#[derive(clap::Args)]
pub struct BenchArgs {
    /// Image file (PNG/JPEG).
    pub image: PathBuf,
    /// Number of timed runs (after one warm-up), >= 1.
    #[arg(long, value_parser = crate::cli::options::range::at_least_one, default_value_t = 20)]
    pub repeat: usize,
    /// Target number of keypoints, >= 1.
    #[arg(long, value_parser = crate::cli::options::range::at_least_one, default_value_t = 1000)]
    pub features: usize,
    /// Write the keypoints to this file: `x y level angle_rad score descriptor_hex` per line.
    #[arg(long)]
    pub dump: Option<PathBuf>,
}

/// Runs the subcommand.
pub fn run(c: Command) -> Result<()> {
    match c {
        Command::Loops(a) => loops(a),
        Command::Bench(a) => bench(a),
    }
}

/// Loads an 8-bit image as intensity in [0, 255].
pub fn load_intensity(path: &Path) -> Result<ImageF32> {
    let img = image::open(path)
        .with_context(|| format!("reading {}", path.display()))?
        .to_rgb8();
    let (w, h) = (img.width() as usize, img.height() as usize);
    let data = img
        .pixels()
        .map(|p| rgb_to_intensity(p[0], p[1], p[2]))
        .collect();
    ImageF32::from_vec(w, h, data).context("image buffer size")
}

/// The default vocabulary, embedded in the binary (trained on rgbid-rendered images).
pub fn default_vocabulary() -> Result<Vocabulary> {
    Ok(Vocabulary::embedded_default()?)
}

fn progress(n: usize, what: &str) -> ProgressBar {
    let pb = ProgressBar::new(n as u64);
    if let Ok(style) =
        ProgressStyle::with_template(&format!("{what} {{bar:40}} {{pos}}/{{len}} {{elapsed}}"))
    {
        pb.set_style(style);
    }
    pb
}

fn median(v: &mut [f64]) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn nearest_pose(gt: &[rgbid::trajectory::TimedPose], t: f64) -> Option<Se3> {
    let p = gt
        .iter()
        .min_by(|a, b| (a.timestamp - t).abs().total_cmp(&(b.timestamp - t).abs()))?;
    ((p.timestamp - t).abs() < 0.02).then_some(p.world_from_camera)
}

fn loops(a: LoopsArgs) -> Result<()> {
    let mut opts = OpenOptions::default();
    super::options::set_camera(&mut opts, a.camera.as_deref(), a.calib_format)?;
    let seq = TumSequence::open(&a.seq, &opts)?;
    let vocab = match &a.vocab {
        Some(p) => Vocabulary::load(p)?,
        None => default_vocabulary()?,
    };
    println!(
        "vocabulary: k={} L={} {} words; camera fx={} fy={} cx={} cy={}; depth factor {}",
        vocab.k(),
        vocab.levels(),
        vocab.num_words(),
        seq.camera.fx,
        seq.camera.fy,
        seq.camera.cx,
        seq.camera.cy,
        seq.depth_factor
    );
    let mut base = LoopDetectorParams::default();
    base.query.min_separation = 30;
    base.direct_index_depth = vocab.levels().saturating_sub(3).max(1);
    let params = a.config.resolve(base, |c| {
        if let Some(v) = a.min_separation {
            c.query.min_separation = v;
        }
        if let Some(v) = a.min_score {
            c.query.min_normalised_score = v;
        }
        Ok(())
    })?;
    log::debug!("loop detector: {params:?}");
    let min_separation = params.query.min_separation;
    let mut det = LoopDetector::new(vocab, params);
    let idx: Vec<usize> = (0..seq.len()).step_by(a.every.max(1)).collect();
    let pb = progress(idx.len(), "keyframes");
    let (mut t_desc, mut t_query) = (Vec::new(), Vec::new());
    let mut loops: Vec<DetectedLoop> = Vec::new();
    let mut stamps = Vec::new();
    for &i in &idx {
        let frame = seq.load(i)?;
        let t0 = Instant::now();
        let desc = det.describe(frame.intensity(), frame.inverse_depth(), &seq.camera, &[])?;
        let t1 = Instant::now();
        let (_, found) = det.insert(desc)?;
        let t2 = Instant::now();
        t_desc.push((t1 - t0).as_secs_f64() * 1e3);
        t_query.push((t2 - t1).as_secs_f64() * 1e3);
        stamps.push(frame.timestamp());
        if let Some(l) = found {
            pb.suspend(|| print_loop(&l, &stamps));
            loops.push(l);
        }
        pb.inc(1);
    }
    pb.finish_and_clear();
    println!(
        "{} keyframes, {} verified loops; median ms per keyframe: ORB+BoW {:.1}, query+verification {:.2}",
        idx.len(),
        loops.len(),
        median(&mut t_desc),
        median(&mut t_query)
    );
    if let Some(gt_path) = &a.gt {
        let gt = rgbid::io::trajectory::read_tum(gt_path)?;
        evaluate(&a, min_separation, &gt, &stamps, &loops);
    }
    Ok(())
}

fn print_loop(l: &DetectedLoop, stamps: &[f64]) {
    let t = l.loop_match.query_from_candidate;
    let q = t.rotation;
    println!(
        "loop {} ({:.3} s) -> {} ({:.3} s): score {:.3} (normalised {:.2}), inliers {}/{}, hull {:.0}%, rms {:.1} mm, \
         query_from_candidate t=[{:.3} {:.3} {:.3}] q=[{:.4} {:.4} {:.4} {:.4}]",
        l.query_id,
        stamps[l.query_id],
        l.candidate_id,
        stamps[l.candidate_id],
        l.candidate.score,
        l.candidate.normalised_score,
        l.loop_match.inliers.len(),
        l.loop_match.matches_3d,
        100.0 * l.loop_match.hull_fraction,
        1e3 * l.loop_match.rms_residual,
        t.translation.x,
        t.translation.y,
        t.translation.z,
        q.x,
        q.y,
        q.z,
        q.w
    );
}

/// Precision / recall of loop detection against ground-truth revisits, and the relative-pose
/// error of the verified loops.
fn evaluate(
    a: &LoopsArgs,
    min_separation: usize,
    gt: &[rgbid::trajectory::TimedPose],
    stamps: &[f64],
    loops: &[DetectedLoop],
) {
    let poses: Vec<Option<Se3>> = stamps.iter().map(|&t| nearest_pose(gt, t)).collect();
    let revisit = |i: usize, j: usize, scale: f64| -> bool {
        match (poses[i], poses[j]) {
            (Some(pi), Some(pj)) => {
                let d = (pi.translation - pj.translation).length();
                let zi = pi.rotation * glam::DVec3::Z;
                let zj = pj.rotation * glam::DVec3::Z;
                let ang = zi.dot(zj).clamp(-1.0, 1.0).acos().to_degrees();
                d < a.gt_distance * scale && ang < a.gt_angle * scale
            }
            _ => false,
        }
    };
    // Queries that have a true revisit among keyframes at least min_separation older.
    let n = stamps.len();
    let with_revisit: Vec<usize> = (0..n)
        .filter(|&i| (0..n).any(|j| j + min_separation <= i && revisit(i, j, 1.0)))
        .collect();
    // A detection is correct if its pair is a revisit under a 2x looser criterion (views
    // that overlap but are slightly outside the strict one are not false positives).
    let correct: Vec<&DetectedLoop> = loops
        .iter()
        .filter(|l| revisit(l.query_id, l.candidate_id, 2.0))
        .collect();
    let recalled = with_revisit
        .iter()
        .filter(|&&i| correct.iter().any(|l| l.query_id == i))
        .count();
    let (mut et, mut er) = (Vec::new(), Vec::new());
    for l in loops {
        if let (Some(pq), Some(pc)) = (poses[l.query_id], poses[l.candidate_id]) {
            let truth = pq.inverse() * pc;
            let d = truth.inverse() * l.loop_match.query_from_candidate;
            et.push(d.translation.length());
            er.push(d.angle().to_degrees());
        }
    }
    println!(
        "ground truth ({} poses): {} queries have a revisit (< {} m, < {} deg, >= {} keyframes apart)",
        gt.len(),
        with_revisit.len(),
        a.gt_distance,
        a.gt_angle,
        min_separation
    );
    let precision = if loops.is_empty() {
        f64::NAN
    } else {
        correct.len() as f64 / loops.len() as f64
    };
    let recall = if with_revisit.is_empty() {
        f64::NAN
    } else {
        recalled as f64 / with_revisit.len() as f64
    };
    println!(
        "precision {:.3} ({} / {} loops), recall {:.3} ({} / {} queries)",
        precision,
        correct.len(),
        loops.len(),
        recall,
        recalled,
        with_revisit.len()
    );
    if !et.is_empty() {
        let max_t = et.iter().copied().fold(0.0, f64::max);
        let max_r = er.iter().copied().fold(0.0, f64::max);
        println!(
            "relative-pose error of verified loops: median {:.1} mm / {:.2} deg, max {:.1} mm / {:.2} deg",
            1e3 * median(&mut et),
            median(&mut er),
            1e3 * max_t,
            max_r
        );
    }
}

fn bench(a: BenchArgs) -> Result<()> {
    let img = load_intensity(&a.image)?;
    let params = OrbParams {
        n_features: a.features,
        ..Default::default()
    };
    let vocab = default_vocabulary()?;
    let f = extract_orb(&img, None, &params)?;
    let mut t_orb = Vec::new();
    let mut t_bow = Vec::new();
    for _ in 0..a.repeat.max(1) {
        let t0 = Instant::now();
        let f = extract_orb(&img, None, &params)?;
        let t1 = Instant::now();
        let _ = vocab.transform(&f.descriptors, 2);
        t_orb.push((t1 - t0).as_secs_f64() * 1e3);
        t_bow.push(t1.elapsed().as_secs_f64() * 1e3);
    }
    if let Some(path) = &a.dump {
        let mut text = String::new();
        for (k, d) in f.keypoints.iter().zip(f.descriptors.iter()) {
            let hex: String = d.to_bytes().iter().map(|b| format!("{b:02x}")).collect();
            text.push_str(&format!(
                "{} {} {} {} {} {}\n",
                k.uv.x, k.uv.y, k.level, k.angle, k.score, hex
            ));
        }
        std::fs::write(path, text).with_context(|| format!("writing {}", path.display()))?;
    }
    println!(
        "{}x{}: {} keypoints; median ORB {:.2} ms, BoW ({} words) {:.2} ms, over {} runs on {} threads",
        img.width(),
        img.height(),
        f.len(),
        median(&mut t_orb),
        vocab.num_words(),
        median(&mut t_bow),
        a.repeat.max(1),
        rayon::current_num_threads()
    );
    Ok(())
}
