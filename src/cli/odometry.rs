//! `rgbid odometry`: dense RGB-D odometry over a TUM-layout sequence folder.

use std::io::Write;
use std::path::PathBuf;

use anyhow::{Context, Result};
use indicatif::{ProgressBar, ProgressStyle};
use rgbid::gpu::select_backend;
use rgbid::io::trajectory::{write_trajectory, TrajectoryFormat};
use rgbid::io::tum::{OpenOptions, TumSequence};
use rgbid::io::CalibFormat;
use rgbid::io::Layout;
use rgbid::odometry::{ModelOdometry, ModelParams, Odometry, OdometryError, TrackResult};
use rgbid::trajectory::TimedPose;
use rgbid::tsdf::TsdfParams;

use super::options::{range, BackendArgs, ConfigArgs, OdometryOptions};
use rgbid::io::settings::Provenance;

/// Arguments of `rgbid odometry`.
#[derive(clap::Args)]
pub struct Args {
    /// Sequence folder: TUM layout (rgb.txt + depth.txt or associations.txt), or ETH3D,
    /// 7-Scenes, Replica (see --format).
    pub sequence: PathBuf,
    /// Output trajectory (world_from_camera, see --traj-format; the first pose is the ground
    /// truth's first pose when the folder has ground truth, else identity). The configuration,
    /// version, backend and command line go to `<OUT>.json` beside it.
    #[arg(long, short, default_value = "trajectory.txt")]
    pub out: PathBuf,
    /// Format of the output trajectory: tum, kitti (also writes `<stem>.times.txt`), euroc
    /// [default: from the extension: .csv euroc, .kitti kitti, else tum].
    #[arg(long, value_enum)]
    pub traj_format: Option<TrajectoryFormat>,
    /// Camera: a preset (default, tum_fr1, tum_fr2, tum_fr3, icl_nuim, 7scenes, replica) or a
    /// camera file (calib.txt, OpenCV / ORB-SLAM .yaml, or `key = value` lines). Default: the layout's own camera (ETH3D calibration.txt, the
    /// 7scenes or replica preset), else calib.txt beside the sequence, else `default`.
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
    /// Layout of the sequence folder: tum (also Bonn, ICL-NUIM), eth3d, 7scenes (one seq-NN
    /// folder), scannet (the exporter's color/ depth/ pose/ intrinsic/), replica (NICE-SLAM's
    /// rendering) [default: detected from its content].
    #[arg(long, value_enum)]
    pub format: Option<Layout>,
    /// Frame rate of layouts without time stamps (7scenes, replica), Hz (> 0).
    #[arg(long, value_parser = range::positive, default_value_t = 30.0)]
    pub fps: f64,
    /// Seconds of input (frame time stamps) between checkpoints: the trajectory so far
    /// replaces the output file atomically (and the CSV is flushed), so a run killed later
    /// leaves it readable; > 0 [default: 5].
    #[arg(long, value_parser = range::positive, default_value_t = super::outputs::CHECKPOINT_EVERY_S)]
    pub checkpoint_every: f64,
    /// Per-frame CSV of statistics (time per stage, sigma, nu, iterations, covisibility,
    /// condition number).
    #[arg(long)]
    pub csv: Option<PathBuf>,
    /// Process at most this many frames (>= 1).
    #[arg(long, value_parser = range::at_least_one)]
    pub max_frames: Option<usize>,
    /// Also log the run to rerun: `save:FILE.rrd` writes a recording, `connect` streams to a
    /// running viewer at 127.0.0.1:9876, `connect=HOST:PORT` (or a `rerun+http://` URL)
    /// elsewhere. Camera poses and pinhole, images (depth in metres) and the per-frame figures
    /// (the --csv columns), on the timelines `frame` (index) and `time` (time stamp, s). Needs
    /// the `rerun` build feature.
    #[arg(long, value_name = "save:FILE.rrd|connect[=ADDR]", value_parser = super::rerun::parse_spec)]
    pub rerun: Option<super::rerun::RerunSpec>,
    /// What each frame is aligned to: `frame` (a reference frame, replaced when the dense
    /// covisibility drops below the threshold; thesis 6.4.1) or `model` (KinectFusion's
    /// frame-to-model tracking: intensity and inverse depth ray cast from a TSDF volume of the
    /// frames tracked so far, at the previous frame's pose; each tracked frame is then
    /// integrated at its estimate). The residuals are the same in both.
    #[arg(long, value_enum, default_value_t = Reference::Frame)]
    pub reference: Reference,
    /// Voxel edge of the model with `--reference model`, metres (> 0; depths 0.3-4 m are
    /// integrated and cast).
    #[arg(long, value_parser = range::positive, default_value_t = 0.02)]
    pub voxel: f64,
    /// Pyramid level at which the model is ray cast with `--reference model` (0 = full
    /// resolution, 1 = half, ...; 0 to 7, below --levels). The odometry reads the reference
    /// from its finest optimised level on (level 1 for 640x480 input).
    #[arg(long, value_parser = range::pyramid_level, default_value_t = 1)]
    pub model_level: usize,
    /// With `--reference model`: leave pixels where the cast finds no surface empty, instead
    /// of filling them with the previous frame's intensity and inverse depth.
    #[arg(long)]
    pub no_model_fill: bool,
    /// Configuration: an `OdometryConfig` file (`rgbid config dump --command odometry`).
    #[command(flatten)]
    pub config: ConfigArgs,
    #[command(flatten)]
    pub odometry: OdometryOptions,
    #[command(flatten)]
    pub backend: BackendArgs,
}

/// What `rgbid odometry` aligns each frame to.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Reference {
    /// A reference frame (frame-to-reference tracking, the default).
    Frame,
    /// Ray casts of a TSDF model (frame-to-model tracking).
    Model,
}

/// The odometry of either reference mode.
enum Tracking {
    Frame(Box<Odometry>),
    Model(Box<ModelOdometry>),
}

impl Tracking {
    fn set_initial_pose(&mut self, world_from_camera: rgbid::geometry::Se3) {
        match self {
            Tracking::Frame(o) => o.set_initial_pose(world_from_camera),
            Tracking::Model(o) => o.set_initial_pose(world_from_camera),
        }
    }

    /// The tracking result and, with a model, its ray cast and integration times (ms).
    fn track(
        &mut self,
        frame: &rgbid::image::RgbdFrame,
    ) -> Result<(TrackResult, Option<(f64, f64)>), OdometryError> {
        match self {
            Tracking::Frame(o) => Ok((o.track(frame)?, None)),
            Tracking::Model(o) => {
                let r = o.track(frame)?;
                Ok((r.track, Some((r.model.ray_cast_ms, r.model.integrate_ms))))
            }
        }
    }
}

/// Runs the subcommand.
pub fn run(args: Args) -> Result<()> {
    let config = args.odometry.config(&args.config)?;
    let mut opts = OpenOptions {
        max_frames: args.max_frames,
        layout: args.format,
        frame_rate: args.fps,
        ..Default::default()
    };
    super::options::set_camera(&mut opts, args.camera.as_deref(), args.calib_format)?;
    let seq = TumSequence::open(&args.sequence, &opts)?;
    // Output locations are checked before any frame runs; the sequence's own files are
    // never outputs.
    let inputs: Vec<&std::path::Path> = [&seq.groundtruth]
        .into_iter()
        .flatten()
        .map(|p| p.as_path())
        .collect();
    super::outputs::output_file(&args.out, "--out", &inputs)?;
    if let Some(p) = &args.csv {
        super::outputs::output_file(p, "--csv", &inputs)?;
    }
    if let Some(p) = args.rerun.as_ref().and_then(|r| r.file()) {
        super::outputs::output_file(p, "--rerun", &inputs)?;
    }
    let mut rerun = match &args.rerun {
        Some(spec) => Some(super::rerun::Recorder::open(spec, "rgbid odometry")?),
        None => None,
    };
    let stop = super::outputs::Stop::install(|| {})?;
    let backend = select_backend(args.backend.backend, args.backend.adapter.as_deref())?;
    log::info!("{} frames, backend {}", seq.len(), backend.name());
    // The provenance does not change during the run: written first, it describes every
    // checkpoint of the trajectory; the run's summary is added at the end.
    let provenance = Provenance::new(&config, &backend)?;
    let sidecar = provenance.write_sidecar(&args.out)?;
    // Said now, so that a long run can be stopped, and again with the outcome (exit code 3).
    let input_warning = seq.depth_range_warning().map(str::to_owned);
    if let Some(w) = &input_warning {
        log::warn!("{w}");
    }
    let format = args
        .traj_format
        .unwrap_or_else(|| TrajectoryFormat::from_extension(&args.out));
    let mut odo = match args.reference {
        Reference::Frame => Tracking::Frame(Box::new(Odometry::new(
            config.clone(),
            seq.camera,
            &backend,
        )?)),
        Reference::Model => {
            let params = ModelParams {
                tsdf: TsdfParams {
                    voxel_size: args.voxel,
                    ..TsdfParams::default()
                },
                cast_level: args.model_level,
                fill_holes: !args.no_model_fill,
            };
            Tracking::Model(Box::new(ModelOdometry::new(
                config.clone(),
                params,
                seq.camera,
                &backend,
            )?))
        }
    };
    let groundtruth = seq.ground_truth()?;
    if let Some(gt) = &groundtruth {
        if let (Some(first), Some(e)) = (gt.first(), seq.entries.first()) {
            // Start at the ground truth's pose nearest to the first frame, so that the estimate
            // and the ground truth share a frame even before alignment.
            let near = gt
                .iter()
                .min_by(|a, b| {
                    (a.timestamp - e.timestamp)
                        .abs()
                        .total_cmp(&(b.timestamp - e.timestamp).abs())
                })
                .unwrap_or(first);
            odo.set_initial_pose(near.world_from_camera);
        }
    }
    let mut csv = match &args.csv {
        Some(p) => {
            let mut f = std::io::BufWriter::new(
                std::fs::File::create(p).with_context(|| format!("{}", p.display()))?,
            );
            writeln!(f, "index,timestamp,pyramid_ms,scale_ms,reduce_ms,solve_ms,covisibility_ms,covariance_ms,total_ms,iterations,sigma_photo,sigma_geo,nu,covisibility,condition_number,new_reference,status,level_iterations,mu_photo,mu_geo,model_cast_ms,model_integrate_ms")?;
            Some(f)
        }
        None => None,
    };
    let bar = ProgressBar::new(seq.len() as u64);
    bar.set_style(
        ProgressStyle::with_template("{bar:40} {pos}/{len} frames {per_sec} eta {eta} {msg}")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    let mut poses: Vec<TimedPose> = Vec::with_capacity(seq.len());
    let mut failures = 0usize;
    let mut outcome: Result<()> = Ok(());
    let mut last_pose = None;
    let mut interrupted = false;
    let mut skips = super::outputs::Skips::default();
    let mut checkpoints = super::outputs::Checkpoints::new(args.checkpoint_every);
    let mut frames = super::ahead::ReadAhead::spawn(seq.len(), {
        let seq = seq.clone();
        move |i| seq.load(i)
    })?;
    for i in 0..seq.len() {
        if stop.requested() {
            interrupted = true;
            break;
        }
        let loaded = match frames.get(i) {
            Ok((loaded, _ms)) => loaded,
            Err(e) => {
                outcome = Err(e);
                break;
            }
        };
        let frame = match loaded {
            Ok(f) => f,
            Err(e) if super::outputs::frame_content_error(&e) => {
                if let Some(stop) = skips.skip(i, anyhow::Error::new(e)) {
                    outcome = Err(stop);
                    break;
                }
                bar.inc(1);
                continue;
            }
            Err(e) => {
                outcome = Err(anyhow::Error::new(e).context(format!("frame {i}")));
                break;
            }
        };
        let tracked = odo.track(&frame);
        if let Some(rr) = rerun.as_mut() {
            rr.odometry_frame(i, &frame, &seq.camera, tracked.as_ref().ok().map(|r| &r.0));
        }
        match tracked {
            Ok((r, model)) => {
                last_pose = Some(r.world_from_camera);
                poses.push(TimedPose {
                    timestamp: frame.timestamp(),
                    world_from_camera: r.world_from_camera,
                });
                if let Some(f) = csv.as_mut() {
                    let s = &r.stats;
                    let t = &s.times;
                    writeln!(
                        f,
                        "{},{:.6},{:.3},{:.3},{:.3},{:.3},{:.3},{:.3},{:.3},{},{:.5},{:.7},{:.3},{:.4},{:.3e},{},ok,{},{:.4},{:.7},{},{}",
                        s.index, s.timestamp, t.pyramid_ms, t.scale_ms, t.reduce_ms, t.solve_ms, t.covisibility_ms,
                        t.covariance_ms, t.total_ms, s.iterations, s.sigma_photo, s.sigma_geo, s.nu, s.covisibility,
                        s.condition_number, u8::from(s.new_reference),
                        // Coarsest level first, e.g. `10 8 6`.
                        s.level_iterations.iter().map(|n| n.to_string()).collect::<Vec<_>>().join(" "),
                        s.mu_photo, s.mu_geo,
                        model.map_or(String::new(), |m| format!("{:.3}", m.0)),
                        model.map_or(String::new(), |m| format!("{:.3}", m.1)),
                    )?;
                }
            }
            Err(OdometryError::TrackingFailed(m)) => {
                failures += 1;
                log::warn!(
                    "frame {i} ({:.3} s): {m}; keeping the previous pose",
                    frame.timestamp()
                );
                if let Some(p) = last_pose {
                    poses.push(TimedPose {
                        timestamp: frame.timestamp(),
                        world_from_camera: p,
                    });
                }
                if let Some(f) = csv.as_mut() {
                    writeln!(
                        f,
                        "{i},{:.6},,,,,,,,,,,,,,,tracking_failed,,,,,",
                        frame.timestamp()
                    )?;
                }
            }
            Err(e) => {
                outcome = Err(anyhow::Error::new(e).context(format!("frame {i}")));
                break;
            }
        }
        bar.inc(1);
        if checkpoints.due(frame.timestamp()) {
            let written = match csv.as_mut() {
                Some(f) => f.flush().with_context(|| {
                    format!(
                        "{}",
                        args.csv.as_deref().unwrap_or(args.out.as_path()).display()
                    )
                }),
                None => Ok(()),
            }
            .and_then(|()| {
                write_trajectory(&args.out, &poses, format).map_err(anyhow::Error::from)
            });
            if let Err(e) = written {
                // The trajectory file holds the previous checkpoint (it is replaced whole).
                outcome = Err(e.context(format!(
                    "checkpoint after frame {i} (the previous checkpoint is kept)"
                )));
                break;
            }
        }
    }
    drop(frames);
    bar.finish_and_clear();
    // Whatever happened, keep what was computed.
    if let Err(e) = write_trajectory(&args.out, &poses, format) {
        let kept = format!("{} keeps its last checkpoint", args.out.display());
        return Err(match outcome {
            Err(first) => first.context(format!(
                "the final trajectory could not be written either ({}); {kept}",
                super::outcome::message(&anyhow::Error::new(e))
            )),
            Ok(()) => anyhow::Error::new(e).context(format!("writing the trajectory; {kept}")),
        });
    }
    if let Some(f) = csv.as_mut() {
        f.flush().with_context(|| {
            format!(
                "{}",
                args.csv.as_deref().unwrap_or(args.out.as_path()).display()
            )
        })?;
    }
    println!("wrote {} poses to {}", poses.len(), args.out.display());
    if failures > 0 {
        println!("{failures} frames failed to track (see the log)");
    }
    let mut summary = Summary {
        status: match (&outcome, interrupted) {
            (Err(e), _) => format!("failed: {}", super::outcome::message(e)),
            (Ok(()), true) => "interrupted".into(),
            (Ok(()), false) => "complete".into(),
        },
        frames: seq.len(),
        poses: poses.len(),
        skipped_frames: skips.count,
        failed_to_track: failures,
        reference: args.reference,
        model: (args.reference == Reference::Model).then_some(ModelSummary {
            voxel_m: args.voxel,
            cast_level: args.model_level,
            fill_holes: !args.no_model_fill,
        }),
        warnings: input_warning.into_iter().collect(),
    };
    if let Some(w) = skips.warning() {
        summary
            .warnings
            .push(format!("{w} (counted in {})", sidecar.display()));
    }
    if failures > 0 {
        summary
            .warnings
            .push(format!("{failures} frames failed to track"));
    }
    if let Some(Err(e)) = rerun.map(|r| r.finish()) {
        summary.warnings.push(e.to_string());
    }
    if outcome.is_ok() && !interrupted {
        if let Some(gt) = &groundtruth {
            // The trajectory is written and complete: an evaluation that cannot be done is a
            // warning (exit code 3), not an error.
            if let Err(e) = crate::cli::eval::print_against(gt, &args.out) {
                summary.warnings.push(format!(
                    "trajectory not evaluated: {}",
                    super::outcome::message(&e)
                ));
            }
        }
    }
    let written = provenance.write_sidecar_with_summary(&args.out, &summary);
    outcome?;
    written?;
    if interrupted {
        return Err(super::outcome::Interrupted {
            out: Some(args.out),
        }
        .into());
    }
    super::outcome::warnings(summary.warnings)
}

/// What a run did, under `summary` in the trajectory's sidecar `<OUT>.json`.
#[derive(serde::Serialize)]
struct Summary {
    /// `complete`, `interrupted` or `failed: <error>`.
    status: String,
    /// Frames of the sequence (or of `--max-frames`).
    frames: usize,
    /// Poses written to the trajectory.
    poses: usize,
    /// Frames skipped because their images could not be used (corrupt, wrongly sized, no
    /// valid depth, an implausible depth scale): no pose for them.
    skipped_frames: usize,
    /// Frames whose tracking failed (they keep the previous pose).
    failed_to_track: usize,
    /// What the frames were aligned to (`--reference`).
    reference: Reference,
    /// The model's options with `--reference model`.
    #[serde(skip_serializing_if = "Option::is_none")]
    model: Option<ModelSummary>,
    /// The warnings of exit code 3, as printed.
    warnings: Vec<String>,
}

/// The options of frame-to-model tracking, in the run's summary.
#[derive(serde::Serialize)]
struct ModelSummary {
    /// Voxel edge, metres.
    voxel_m: f64,
    /// Pyramid level of the ray cast (0 = full resolution).
    cast_level: usize,
    /// Holes of the cast filled from the previous frame.
    fill_holes: bool,
}
