//! `rgbid odometry`: dense RGB-D odometry over a TUM-layout sequence folder.

use std::io::Write;
use std::path::PathBuf;

use anyhow::{Context, Result};
use indicatif::{ProgressBar, ProgressStyle};
use rgbid::gpu::{select_backend, BackendChoice};
use rgbid::io::trajectory::write_tum;
use rgbid::io::tum::{OpenOptions, TumSequence};
use rgbid::odometry::{
    Estimator, GeometricParam, Odometry, OdometryConfig, OdometryError, ScaleMethod, Terms,
};
use rgbid::trajectory::TimedPose;

/// Options shared by every command that runs the odometry.
#[derive(clap::Args, Clone, Debug)]
pub struct OdometryOptions {
    /// JSON file with odometry options (see `OdometryConfig`; missing keys keep defaults).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Robust estimator.
    #[arg(long, value_enum)]
    pub estimator: Option<Estimator>,
    /// Scale estimation: ml (maximum likelihood), mad, or fixed (sigmaFix).
    #[arg(long, value_enum)]
    pub scale: Option<ScaleMethod>,
    /// Residual terms.
    #[arg(long, value_enum)]
    pub terms: Option<Terms>,
    /// Geometric error parametrisation.
    #[arg(long, value_enum)]
    pub geometric: Option<GeometricParam>,
    /// Pyramid levels.
    #[arg(long)]
    pub levels: Option<usize>,
    /// Finest pyramid level used (0 = full resolution).
    #[arg(long)]
    pub stop_level: Option<usize>,
    /// Levels wider than this many pixels are not optimised (default 320: at 640x480 the
    /// finest optimised level is 320x240); 0 optimises every level down to --stop-level.
    #[arg(long)]
    pub max_width: Option<usize>,
    /// Align every frame to the previous one (no reference-frame keeping).
    #[arg(long)]
    pub frame_to_frame: bool,
    /// Covisibility ratio below which the reference frame is switched.
    #[arg(long)]
    pub covisibility: Option<f64>,
    /// Compute backend: auto (hardware GPU, else CPU), gpu (any adapter, lavapipe included), cpu.
    #[arg(long, value_enum, default_value_t = BackendChoice::Auto)]
    pub backend: BackendChoice,
    /// Use the GPU adapter whose name contains this (case-insensitive).
    #[arg(long)]
    pub adapter: Option<String>,
}

impl OdometryOptions {
    /// The configuration these options describe.
    pub fn config(&self) -> Result<OdometryConfig> {
        let mut c = match &self.config {
            Some(p) => OdometryConfig::from_json_file(p)?,
            None => OdometryConfig::default(),
        };
        if let Some(v) = self.estimator {
            c.estimator = v;
        }
        if let Some(v) = self.scale {
            c.scale = v;
        }
        if let Some(v) = self.terms {
            c.terms = v;
        }
        if let Some(v) = self.geometric {
            c.geometric = v;
            if v == GeometricParam::Depth && c.scale == ScaleMethod::Fixed {
                // sigmaFix in depth units: 1 cm.
                c.fixed_sigma_geo = 0.01;
            }
        }
        if let Some(v) = self.levels {
            c.levels = v;
            c.covisibility_level = c.covisibility_level.min(v.saturating_sub(1));
        }
        if let Some(v) = self.stop_level {
            c.stop_level = v;
        }
        if let Some(v) = self.max_width {
            c.max_width = v;
        }
        if self.frame_to_frame {
            c.reference_switch = None;
        } else if let Some(v) = self.covisibility {
            c.reference_switch = Some(v);
        }
        c.validate()?;
        Ok(c)
    }
}

/// Arguments of `rgbid odometry`.
#[derive(clap::Args)]
pub struct Args {
    /// TUM-layout sequence folder (rgb.txt + depth.txt or associations.txt, rgb/, depth/).
    pub sequence: PathBuf,
    /// Output trajectory (TUM format, world_from_camera; the first pose is the ground truth's
    /// first pose when the folder has groundtruth.txt, else identity).
    #[arg(long, short, default_value = "trajectory.txt")]
    pub out: PathBuf,
    /// Camera: a preset (tum_fr1, tum_fr2, tum_fr3, default) or a camera config file.
    /// Default: calib.txt beside the sequence, else the `default` preset.
    #[arg(long)]
    pub camera: Option<String>,
    /// Per-frame CSV of statistics (time per stage, sigma, nu, iterations, covisibility,
    /// condition number).
    #[arg(long)]
    pub csv: Option<PathBuf>,
    /// Process at most this many frames.
    #[arg(long)]
    pub max_frames: Option<usize>,
    #[command(flatten)]
    pub odometry: OdometryOptions,
}

/// Runs the subcommand.
pub fn run(args: Args) -> Result<()> {
    let config = args.odometry.config()?;
    let mut opts = OpenOptions {
        max_frames: args.max_frames,
        ..Default::default()
    };
    if let Some(c) = &args.camera {
        opts.camera = Some(c.parse().with_context(|| format!("camera '{c}'"))?);
    }
    let seq = TumSequence::open(&args.sequence, &opts)?;
    let backend = select_backend(args.odometry.backend, args.odometry.adapter.as_deref())?;
    log::info!("{} frames, backend {}", seq.len(), backend.name());
    let mut odo = Odometry::new(config, seq.camera, &backend)?;
    if let Some(gt) = seq
        .groundtruth
        .as_ref()
        .and_then(|p| rgbid::io::trajectory::read_tum(p).ok())
    {
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
            writeln!(f, "index,timestamp,pyramid_ms,scale_ms,reduce_ms,solve_ms,covisibility_ms,covariance_ms,total_ms,iterations,sigma_photo,sigma_geo,nu,covisibility,condition_number,new_reference,status")?;
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
    for i in 0..seq.len() {
        let frame = match seq.load(i) {
            Ok(f) => f,
            Err(e) => {
                outcome = Err(anyhow::Error::new(e).context(format!("frame {i}")));
                break;
            }
        };
        match odo.track(&frame) {
            Ok(r) => {
                last_pose = Some(r.world_from_camera);
                poses.push(TimedPose {
                    timestamp: frame.timestamp,
                    world_from_camera: r.world_from_camera,
                });
                if let Some(f) = csv.as_mut() {
                    let s = &r.stats;
                    let t = &s.times;
                    writeln!(
                        f,
                        "{},{:.6},{:.3},{:.3},{:.3},{:.3},{:.3},{:.3},{:.3},{},{:.5},{:.7},{:.3},{:.4},{:.3e},{},ok",
                        s.index, s.timestamp, t.pyramid_ms, t.scale_ms, t.reduce_ms, t.solve_ms, t.covisibility_ms,
                        t.covariance_ms, t.total_ms, s.iterations, s.sigma_photo, s.sigma_geo, s.nu, s.covisibility,
                        s.condition_number, u8::from(s.new_reference)
                    )?;
                }
            }
            Err(OdometryError::TrackingFailed(m)) => {
                failures += 1;
                log::warn!(
                    "frame {i} ({:.3} s): {m}; keeping the previous pose",
                    frame.timestamp
                );
                if let Some(p) = last_pose {
                    poses.push(TimedPose {
                        timestamp: frame.timestamp,
                        world_from_camera: p,
                    });
                }
                if let Some(f) = csv.as_mut() {
                    writeln!(
                        f,
                        "{i},{:.6},,,,,,,,,,,,,,,tracking_failed",
                        frame.timestamp
                    )?;
                }
            }
            Err(e) => {
                outcome = Err(anyhow::Error::new(e).context(format!("frame {i}")));
                break;
            }
        }
        bar.inc(1);
    }
    bar.finish_and_clear();
    // Whatever happened, keep what was computed.
    write_tum(&args.out, &poses)?;
    println!("wrote {} poses to {}", poses.len(), args.out.display());
    if failures > 0 {
        println!("{failures} frames failed to track (see the log)");
    }
    outcome?;
    if let Some(gt) = &seq.groundtruth {
        crate::cli::eval::print_against(gt, &args.out)?;
    }
    Ok(())
}
