//! `rgbid segment`: superjut segmentation of frames of a TUM-layout sequence.
//!
//! Writes per frame a colour-coded segment image, a neg-entropy image, one mask per
//! threshold, and one CSV (`superjuts.csv`) with the features of every superjut.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context, Result};
use rgbid::experiments::mesh_change::{run_mesh_change_experiment, MeshChangeConfig};
use rgbid::experiments::segment::{run_change_experiment, ChangeExperimentConfig};
use rgbid::gpu::{select_backend, BackendChoice};
use rgbid::io::tum::{OpenOptions, TumSequence};
use rgbid::segment::{self, NormalParams, SegmentConfig};
use rgbid::synth::SensorModel;

use super::options::{write_sidecar, ConfigArgs};

/// `rgbid segment SEQ ...` segments frames of a sequence; `experiment` is a subcommand.
#[derive(clap::Args)]
#[command(args_conflicts_with_subcommands = true)]
pub struct Args {
    #[command(subcommand)]
    command: Option<Command>,
    #[command(flatten)]
    run: RunArgs,
}

/// Subcommands of `rgbid segment`.
#[derive(clap::Subcommand)]
pub enum Command {
    /// The thesis' changed-environment experiments (figs. 5.6 and 5.10) on generated loops:
    /// ROC AUC of each superjut feature for changed vs static superjuts (moved-object masks as
    /// ground truth), and ORB matching between sessions with and without neg-entropy masks
    /// (precision and recall of RANSAC-verified matches against the true relative pose).
    Experiment(ExperimentArgs),
    /// The thesis' mesh experiment (eq. 5.3, figs. 5.9-5.10) on generated loops: TSDF meshes
    /// of session 0 and of changed sessions (objects moved, removed, added), the changed
    /// session's mesh segmented by its edges; eq. 5.3 ground truth (vertices farther than D
    /// from every session-0 surface), changed-area precision/recall per neg-entropy threshold,
    /// and ORB matching with the projected mesh masks.
    MeshExperiment(MeshExperimentArgs),
}

/// Options of `rgbid segment mesh-experiment`.
#[derive(clap::Args)]
pub struct MeshExperimentArgs {
    /// Scene presets.
    #[arg(long, value_delimiter = ',', default_value = "office,kitchen,lab,home")]
    scenes: Vec<String>,
    /// Scene seeds (each scene with each seed) (any whole number, 0 to 2^64-1).
    #[arg(long, value_parser = crate::cli::options::range::seed, value_delimiter = ',', default_value = "1")]
    seeds: Vec<u64>,
    /// Changed sessions 1..=N compared with session 0 (1 to 1000).
    #[arg(long, value_parser = crate::cli::options::range::sessions, default_value_t = 2)]
    sessions: u32,
    /// Frames per lap of the loop, all integrated into the session's TSDF (>= 1).
    #[arg(long, value_parser = crate::cli::options::range::at_least_one, default_value_t = MeshChangeConfig::default().lap_frames)]
    lap_frames: usize,
    /// Every STEP-th frame starts a matching pair (>= 1).
    #[arg(long, value_parser = crate::cli::options::range::at_least_one, default_value_t = MeshChangeConfig::default().step)]
    step: usize,
    /// The changed-session frame of a pair is OFFSET frames after the reference frame (a whole number >= 0).
    #[arg(long, value_parser = crate::cli::options::range::count, default_value_t = MeshChangeConfig::default().offset)]
    offset: usize,
    /// Image width in pixels (height 3/4 of it) (16 to 16384 pixels).
    #[arg(long, value_parser = crate::cli::options::range::image_side, default_value_t = MeshChangeConfig::default().width)]
    width: u32,
    /// Depth sensor of the rendered frames (see `rgbid segment experiment --help`). The
    /// default, `kinect-native`, gives the 640x480 Kinect's depth resolution the thesis'
    /// meshes were fused from, whatever the rendered width.
    #[arg(long, value_enum, default_value_t = SensorArg::KinectNative)]
    sensor: SensorArg,
    /// TSDF voxel edge, metres (> 0).
    #[arg(long, value_parser = crate::cli::options::range::positive, default_value_t = MeshChangeConfig::default().tsdf.voxel_size)]
    voxel: f64,
    /// Eq. 5.3's distance D, metres (> 0): a changed-session vertex farther than D from every
    /// session-0 surface is changed.
    #[arg(long, value_parser = crate::cli::options::range::positive, default_value_t = MeshChangeConfig::default().change_distance)]
    change_distance: f64,
    /// Neg-entropy thresholds: segments below one are masked as changed (an unmasked run is
    /// always added to the matching) (each in [0, 1]).
    #[arg(long, value_parser = crate::cli::options::range::unit, value_delimiter = ',', default_value = "0.2,0.3,0.4,0.5,0.6,0.7,0.8,0.9")]
    thresholds: Vec<f64>,
    /// Minimum mesh segment size, vertices (>= 1).
    #[arg(long, value_parser = crate::cli::options::range::at_least_one, default_value_t = MeshChangeConfig::default().segment.min_size)]
    min_size: usize,
    /// Where frames are rendered and integrated.
    #[arg(long, value_enum, default_value_t = BackendChoice::Auto)]
    backend: BackendChoice,
    /// Also write the report as JSON here (with a `meta` block; `scripts/results.py`
    /// renders `docs/results/*.json`).
    #[arg(long)]
    json: Option<PathBuf>,
}

/// Options of `rgbid segment experiment`.
#[derive(clap::Args)]
pub struct ExperimentArgs {
    /// Scene presets.
    #[arg(long, value_delimiter = ',', default_value = "office,kitchen,lab")]
    scenes: Vec<String>,
    /// Scene seeds (each scene with each seed) (any whole number, 0 to 2^64-1).
    #[arg(long, value_parser = crate::cli::options::range::seed, value_delimiter = ',', default_value = "1,2")]
    seeds: Vec<u64>,
    /// Changed sessions 1..=N compared with session 0 (1 to 1000).
    #[arg(long, value_parser = crate::cli::options::range::sessions, default_value_t = 2)]
    sessions: u32,
    /// Frames per lap of the loop (30 fps) (>= 1).
    #[arg(long, value_parser = crate::cli::options::range::at_least_one, default_value_t = 300)]
    lap_frames: usize,
    /// Use every STEP-th frame (>= 1).
    #[arg(long, value_parser = crate::cli::options::range::at_least_one, default_value_t = 20)]
    step: usize,
    /// The changed-session frame is OFFSET frames after the reference frame (a whole number >= 0).
    #[arg(long, value_parser = crate::cli::options::range::count, default_value_t = 4)]
    offset: usize,
    /// Image width in pixels (height 3/4 of it) (16 to 16384 pixels).
    #[arg(long, value_parser = crate::cli::options::range::image_side, default_value_t = 320)]
    width: u32,
    /// Depth sensor of the rendered frames: `kinect` (the generator's Kinect-like model:
    /// disparity noise 0.1 px and 1/8 px steps at the rendered image's focal length),
    /// `kinect-native` (the same noise at the 525 px focal length of the 640x480 Kinect,
    /// i.e. a real Kinect's depth resolution whatever the rendered width), or `noiseless`.
    #[arg(long, value_enum, default_value_t = SensorArg::Kinect)]
    sensor: SensorArg,
    /// Fuse the inverse depth of the next FUSE frames (true poses) into each frame before
    /// segmenting it, as SLAM keyframes are fused (0 = single raw frames) (a whole number >= 0).
    #[arg(long, value_parser = crate::cli::options::range::count, default_value_t = 0)]
    fuse: usize,
    /// Neg-entropy thresholds of the masks (an unmasked run is always added) (each in [0, 1]).
    #[arg(long, value_parser = crate::cli::options::range::unit, value_delimiter = ',', default_value = "0.3,0.5,0.6,0.7,0.8,0.9")]
    thresholds: Vec<f64>,
    /// Finite-difference step of the normals, pixels (1 to 64 pixels).
    #[arg(long, value_parser = crate::cli::options::range::pixel_step, default_value_t = NormalParams::default().step)]
    normal_step: u32,
    /// Half-width of the edge-aware inverse-depth smoothing before the normals (0 = none) (0 to 64 pixels).
    #[arg(long, value_parser = crate::cli::options::range::pixel_radius, default_value_t = NormalParams::default().smooth_radius)]
    smooth_radius: u32,
    /// Where the frames are rendered.
    #[arg(long, value_enum, default_value_t = BackendChoice::Auto)]
    backend: BackendChoice,
    /// Also write the report as JSON here.
    #[arg(long)]
    json: Option<PathBuf>,
}

/// Options of segmenting frames of a sequence.
#[derive(clap::Args)]
pub struct RunArgs {
    /// Sequence folder in TUM layout (`rgb.txt` + `depth.txt`, optional `calib.txt`),
    /// read with `rgbid::io::tum::TumSequence`.
    pub seq: Option<PathBuf>,
    /// Frames to segment: a comma-separated list of indices and ranges `a..b` or `a..b:step`
    /// (end exclusive), e.g. `0,10,20..100:20`.
    #[arg(long, default_value = "0")]
    pub frames: String,
    /// Output folder (created if missing).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Neg-entropy thresholds of the masks (each in [0, 1]).
    #[arg(long, value_parser = crate::cli::options::range::unit, value_delimiter = ',', default_value = "0.3,0.5,0.7")]
    pub thresholds: Vec<f64>,
    /// Felzenszwalb-Huttenlocher scale k, > 0 (`k`) [default: 0.6].
    #[arg(long, value_parser = crate::cli::options::range::positive_f32)]
    pub k: Option<f32>,
    /// Minimum superjut size in pixels (`min_size`); >= 1 [default: 200].
    #[arg(long, value_parser = crate::cli::options::range::at_least_one)]
    pub min_size: Option<usize>,
    /// Finite-difference step of the normals, pixels (`normals.step`); 1 to 64 pixels [default: 2].
    #[arg(long, value_parser = crate::cli::options::range::pixel_step)]
    pub normal_step: Option<u32>,
    /// Half-width of the edge-aware inverse-depth smoothing before the normals, pixels
    /// (0 = none) (`normals.smooth_radius`); 0 to 64 pixels [default: 3].
    #[arg(long, value_parser = crate::cli::options::range::pixel_radius)]
    pub smooth_radius: Option<u32>,
    /// Up direction in the camera frame for horizontality, `x,y,z` (normalised) (`up`)
    /// [default: 0,-1,0]; three finite numbers.
    #[arg(long, value_parser = crate::cli::options::range::finite_f32, value_delimiter = ',', allow_hyphen_values = true)]
    pub up: Option<Vec<f32>>,
    /// Configuration: a `SegmentConfig` file (`rgbid config dump --command segment`).
    #[command(flatten)]
    pub config: ConfigArgs,
    /// Where the normal kernel runs.
    #[arg(long, value_enum, default_value_t = BackendChoice::Cpu)]
    pub backend: BackendChoice,
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

fn save_gray(path: &Path, w: usize, h: usize, data: Vec<u8>) -> Result<()> {
    image::GrayImage::from_raw(w as u32, h as u32, data)
        .context("image buffer size")?
        .save(path)
        .with_context(|| format!("writing {}", path.display()))
}

/// Runs the subcommand.
pub fn run(args: Args) -> Result<()> {
    match args.command {
        Some(Command::Experiment(e)) => run_experiment(&e),
        Some(Command::MeshExperiment(e)) => run_mesh_experiment(&e),
        None => run_segment(&args.run),
    }
}

/// Depth sensor models of `rgbid segment experiment --sensor`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
enum SensorArg {
    /// The generator's Kinect-like model at the rendered focal length.
    Kinect,
    /// Kinect-like noise at the 640x480 Kinect's focal length (525 px).
    KinectNative,
    /// No noise, no quantisation, no dropout.
    Noiseless,
}

fn sensor_model(s: SensorArg) -> SensorModel {
    match s {
        SensorArg::Kinect => SensorModel::kinect(),
        SensorArg::KinectNative => SensorModel {
            focal_px: Some(525.0),
            ..SensorModel::kinect()
        },
        SensorArg::Noiseless => SensorModel::noiseless(),
    }
}

fn run_mesh_experiment(a: &MeshExperimentArgs) -> Result<()> {
    let mut config = MeshChangeConfig {
        scenes: a.scenes.clone(),
        seeds: a.seeds.clone(),
        sessions: a.sessions,
        lap_frames: a.lap_frames,
        step: a.step,
        offset: a.offset,
        width: a.width,
        sensor: sensor_model(a.sensor),
        change_distance: a.change_distance,
        thresholds: a.thresholds.clone(),
        ..Default::default()
    };
    config.tsdf.voxel_size = a.voxel;
    config.segment.min_size = a.min_size;
    config.validate()?;
    let backend = select_backend(a.backend, None)?;
    let bar = indicatif::ProgressBar::new(0);
    let t = Instant::now();
    let report = run_mesh_change_experiment(&config, &backend, |done, total| {
        bar.set_length(total as u64);
        bar.set_position(done as u64);
    })?;
    bar.finish_and_clear();
    let wall_s = t.elapsed().as_secs_f64();
    println!("| scene | seed | session | changed objects | vertices | segments | eq. 5.3 changed | generator changed | agreement |");
    println!("|---|---|---|---|---|---|---|---|---|");
    for r in &report.sessions {
        let g = &r.ground_truth;
        println!(
            "| {} | {} | {} | {} | {} | {} | {:.2} m^2 | {:.2} m^2 | {:.3} |",
            r.scene,
            r.seed,
            r.session,
            r.changed_objects,
            r.vertices,
            r.segments,
            g.eq53_changed_m2,
            g.generator_changed_m2,
            g.agreement
        );
    }
    let g = &report.ground_truth;
    println!(
        "\nEq. 5.3 (d = {} m) against the generator's labels: {:.1} of {:.1} m^2 changed by eq. 5.3, {:.1} m^2 on moved/added objects; agreement {:.3}, precision {:.3}, recall {:.3}; {:.2} m^2 off every surface of its own session",
        config.change_distance,
        g.eq53_changed_m2,
        g.area_m2,
        g.generator_changed_m2,
        g.agreement,
        g.eq53_precision,
        g.eq53_recall,
        g.off_surface_m2
    );
    println!("\nChanged-area detection (segments with neg-entropy below the threshold masked; area-weighted):");
    println!("| threshold | masked area | precision | recall (eq. 5.3) | recall (generator) | unchanged area kept |");
    println!("|---|---|---|---|---|---|");
    for d in &report.detection {
        println!(
            "| < {:.2} | {:.3} | {:.3} | {:.3} | {:.3} | {:.3} |",
            d.threshold, d.masked_share, d.precision, d.recall, d.recall_generator, d.static_kept
        );
    }
    println!(
        "\nMatching session 0 against changed sessions, mesh masks ({} pairs, {} see changed objects):",
        report.pairs, report.pairs_with_changes
    );
    print_matching(&report.matching);
    print_cluttered(&report.cluttered_views);
    println!(
        "\nmedian per session: render + integrate {:.1} s, mesh {:.1} s, segmentation {:.1} s, ground truth {:.1} s; {:.0} s in all",
        report.integrate_s, report.extract_s, report.segment_s, report.ground_truth_s, wall_s
    );
    if let Some(p) = &a.json {
        #[derive(serde::Serialize)]
        struct Body<'a> {
            config: &'a MeshChangeConfig,
            sensor: String,
            wall_s: f64,
            #[serde(flatten)]
            report: &'a rgbid::experiments::mesh_change::MeshChangeReport,
        }
        let adapters = match &backend {
            rgbid::gpu::ComputeBackend::Gpu(g) => vec![g.adapter_info().name.clone()],
            rgbid::gpu::ComputeBackend::Cpu => Vec::new(),
        };
        super::report::write(
            p,
            "mesh-change",
            &super::report::meta(adapters),
            &Body {
                config: &config,
                sensor: format!("{:?}", a.sensor),
                wall_s,
                report: &report,
            },
        )?;
    }
    Ok(())
}

fn run_experiment(a: &ExperimentArgs) -> Result<()> {
    let mut config = ChangeExperimentConfig {
        scenes: a.scenes.clone(),
        seeds: a.seeds.clone(),
        sessions: a.sessions,
        lap_frames: a.lap_frames,
        step: a.step,
        offset: a.offset,
        width: a.width,
        sensor: match a.sensor {
            SensorArg::Kinect => SensorModel::kinect(),
            SensorArg::KinectNative => SensorModel {
                focal_px: Some(525.0),
                ..SensorModel::kinect()
            },
            SensorArg::Noiseless => SensorModel::noiseless(),
        },
        fuse: a.fuse,
        thresholds: a.thresholds.clone(),
        ..Default::default()
    };
    config.segment.normals.step = a.normal_step;
    config.segment.normals.smooth_radius = a.smooth_radius;
    config.validate()?;
    let backend = select_backend(a.backend, None)?;
    let bar = indicatif::ProgressBar::new(0);
    let report = run_change_experiment(&config, &backend, |done, total| {
        bar.set_length(total as u64);
        bar.set_position(done as u64);
    })?;
    bar.finish_and_clear();
    println!(
        "{} frame pairs ({} see changed objects); superjuts: {} changed, {} static",
        report.pairs, report.pairs_with_changes, report.changed_superjuts, report.static_superjuts
    );
    println!("\nSeparability (ROC AUC, higher value = static; 0.5 = chance):");
    println!("| feature | AUC |\n|---|---|");
    for f in &report.features {
        println!("| {} | {:.3} |", f.feature, f.auc);
    }
    println!("\nMatching session 0 against changed sessions (RANSAC-verified matches):");
    print_matching(&report.matching);
    print_cluttered(&report.cluttered_views);
    println!(
        "\nmedian per frame: segmentation {:.1} ms, ORB {:.1} ms ({}x{})",
        report.segment_ms,
        report.orb_ms,
        a.width,
        a.width * 3 / 4
    );
    if let Some(p) = &a.json {
        std::fs::write(p, serde_json::to_string_pretty(&report)?)
            .with_context(|| format!("writing {}", p.display()))?;
    }
    Ok(())
}

fn run_segment(args: &RunArgs) -> Result<()> {
    let (Some(seq_dir), Some(out)) = (&args.seq, &args.out) else {
        bail!("usage: rgbid segment SEQ --out DIR [--frames ...] (or rgbid segment experiment)");
    };
    let seq = TumSequence::open(seq_dir, &OpenOptions::default())?;
    log::info!(
        "{}: {} frames, camera from {}",
        seq_dir.display(),
        seq.len(),
        seq.camera_source
    );
    let frames = parse_frames(&args.frames)?;
    if frames.is_empty() {
        bail!("--frames selects no frame");
    }
    if let Some(&bad) = frames.iter().find(|&&f| f >= seq.len()) {
        bail!(
            "frame {bad} out of range: the sequence has {} frames",
            seq.len()
        );
    }
    let cam = seq.undistorted_camera();
    let cfg = args.config.resolve(SegmentConfig::default(), |c| {
        if let Some(v) = args.k {
            c.k = v;
        }
        if let Some(v) = args.min_size {
            c.min_size = v;
        }
        if let Some(v) = args.normal_step {
            c.normals.step = v;
        }
        if let Some(v) = args.smooth_radius {
            c.normals.smooth_radius = v;
        }
        if let Some(up) = &args.up {
            if up.len() != 3 {
                bail!("--up needs 3 values");
            }
            c.up = [up[0], up[1], up[2]];
        }
        Ok(())
    })?;
    let mut cfg = cfg;
    let ul = cfg.up.iter().map(|v| v * v).sum::<f32>().sqrt();
    if !(ul > 0.0) {
        bail!("up must be non-zero");
    }
    cfg.up = cfg.up.map(|v| v / ul);
    cfg.validate()?;
    let backend = select_backend(args.backend, None)?;
    log::info!("normals on {}", backend.name());
    let mut normals = segment::normal_kernels(&backend)?;
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let csv_path = out.join("superjuts.csv");
    write_sidecar(&csv_path, &cfg, &backend)?;
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
    let mut segmenter = segment::Segmenter::new();
    for &f in &frames {
        let frame = seq.load(f)?;
        let (t, intensity, inv) = (frame.timestamp(), frame.intensity(), frame.inverse_depth());
        let t0 = Instant::now();
        let n = normals.compute(inv, &cam, &cfg.normals)?;
        let juts = segmenter.segment_with_normals(intensity, inv, &cam, n, &cfg)?;
        times.push(t0.elapsed().as_secs_f64() * 1e3);
        let (w, h) = (juts.width, juts.height);
        let stem = format!("frame_{f:05}");
        image::RgbImage::from_raw(w as u32, h as u32, juts.colour_image())
            .context("image buffer size")?
            .save(out.join(format!("{stem}_segments.png")))?;
        let ne = juts
            .neg_entropy_image()
            .data()
            .iter()
            .map(|v| {
                if v.is_nan() {
                    0
                } else {
                    (v * 255.0).round() as u8
                }
            })
            .collect();
        save_gray(&out.join(format!("{stem}_negentropy.png")), w, h, ne)?;
        for &th in &args.thresholds {
            let m = juts.mask(th);
            save_gray(&out.join(format!("{stem}_mask_{th:.2}.png")), w, h, m.data)?;
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
        out.display(),
        times[times.len() / 2],
        backend.name()
    );
    Ok(())
}

/// Prints matching rows as a Markdown table (header included).
/// The matching tables over the views of moved clutter, one per share of changed matches.
fn print_cluttered(views: &[rgbid::experiments::segment::ClutteredViews]) {
    for c in views {
        println!(
            "\nViews of moved clutter: the {} frame pairs in which changed objects carry >= {:.0} % of the unmasked matches:",
            c.pairs,
            100.0 * c.min_changed_share
        );
        if c.pairs > 0 {
            print_matching(&c.matching);
        }
    }
}

fn print_matching(rows: &[rgbid::experiments::segment::MatchingRow]) {
    println!(
        "| neg-entropy mask | kept keypoints | matches | on changed objects | verified | inlier ratio | correct | precision | recall | pairs with pose ok |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|");
    for r in rows {
        let t = r
            .threshold
            .map_or("none".to_string(), |t| format!(">= {t:.2}"));
        println!(
            "| {t} | {:.2} | {} | {} ({:.1} %) | {} | {:.3} | {} | {:.3} | {:.3} | {} |",
            r.kept_keypoints,
            r.matches,
            r.matches_on_changed,
            100.0 * r.matches_on_changed as f64 / r.matches.max(1) as f64,
            r.verified,
            r.inlier_ratio,
            r.correct,
            r.precision,
            r.recall,
            r.pairs_pose_ok
        );
    }
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
