//! `rgbid synth`: renders a synthetic RGB-D (or omnidirectional) sequence with exact ground
//! truth into a dataset folder (TUM, or another layout with `--layout`), or times the renderer
//! on each backend (`--bench`).

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

use anyhow::{bail, Context, Result};
use indicatif::{ProgressBar, ProgressStyle};
use rgbid::camera::{PinholeCamera, UnifiedCamera};
use rgbid::gpu::{select_backend, BackendChoice, ComputeBackend};
use rgbid::io::Layout;
use rgbid::synth::layout_export::LayoutWriter;
use rgbid::synth::trajectory::{TrajectoryKind, TRAJECTORIES};
use rgbid::synth::tum_export::TumWriter;
use rgbid::synth::{
    CameraModel, RenderBackend, Scene, SensorModel, Sequence, SequenceConfig, Trajectory, PRESETS,
};

/// Camera kinds of `--camera`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum CameraKind {
    /// Kinect-like pinhole camera (fx = fy = 525 at 640x480, scaled with the width).
    Pinhole,
    /// Catadioptric camera, unified sphere model (xi 0.9, circular field of view).
    Omni,
}

/// Arguments of `rgbid synth`.
#[derive(clap::Args)]
pub struct Args {
    /// Scene preset (office, kitchen, corridor, lab, home; hall and stairwell: long corridors
    /// walked along an open route, the stairwell with a flight of stairs for `stairs`).
    #[arg(long, default_value = "office")]
    scene: String,
    /// Trajectory (handheld, slow, fast, loop, walk-head, walk-chest, stairs, robot).
    #[arg(long, default_value = "handheld")]
    trajectory: String,
    /// Number of frames (>= 1).
    #[arg(long, value_parser = super::options::range::at_least_one, default_value_t = 300)]
    frames: usize,
    /// Frame rate (frames per second, > 0).
    #[arg(long, value_parser = super::options::range::positive, default_value_t = 30.0)]
    fps: f64,
    /// Camera model.
    #[arg(long, value_enum, default_value_t = CameraKind::Pinhole)]
    camera: CameraKind,
    /// Image width in pixels (16 to 16384 pixels).
    #[arg(long, value_parser = crate::cli::options::range::image_side, default_value_t = 640)]
    width: u32,
    /// Image height in pixels (default: 3/4 of the width, as `rgbid slam --synth` and
    /// `rgbid demo` use) (16 to 16384 pixels).
    #[arg(long, value_parser = crate::cli::options::range::image_side)]
    height: Option<u32>,
    /// Seed of the scene, trajectory and noise (any whole number, 0 to 2^64-1).
    #[arg(long, value_parser = crate::cli::options::range::seed, default_value_t = 7)]
    seed: u64,
    /// Folder layout of the output: tum (also ICL-NUIM's TUM variant), eth3d, 7scenes,
    /// scannet (colour written at twice the depth size with its own intrinsics), replica
    /// (NICE-SLAM's). 7scenes and replica folders also get a DROID-SLAM `calib.txt` for
    /// `--camera DIR/calib.txt --calib-format droid`. Layouts other than tum need the pinhole
    /// camera and one session without noise-free masks.
    #[arg(long, value_enum, default_value_t = Layout::Tum)]
    layout: Layout,
    /// Output folder (required unless --bench).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Noise-free depth and colour (no dropout, no quantisation beyond 8/16-bit storage).
    #[arg(long)]
    no_noise: bool,
    /// Render this many sessions of the changing environment (session_00, session_01, ...
    /// under --out; sessions > 0 move, remove or add objects and write moved-object masks).
    #[arg(long, value_parser = crate::cli::options::range::sessions, default_value_t = 1)]
    sessions: u32,
    /// Smooth auto-exposure gain changes between frames.
    #[arg(long)]
    exposure_changes: bool,
    /// Motion blur: sub-frame renders averaged over a 1/60 s exposure (0 = off) (0 to 64).
    #[arg(long, value_parser = crate::cli::options::range::sub_frames, default_value_t = 0)]
    motion_blur: usize,
    /// Where the ray casting runs (auto: a hardware GPU if present, else the CPU).
    #[arg(long, value_enum, default_value_t = BackendChoice::Auto)]
    backend: BackendChoice,
    /// Case-insensitive substring of the GPU adapter name to use.
    #[arg(long)]
    adapter: Option<String>,
    /// Time rendering `--frames` frames on every available backend (CPU, and any GPU
    /// adapter, software included) without writing files, and print the seconds.
    #[arg(long)]
    bench: bool,
}

impl Args {
    /// The image height: `--height`, else 3/4 of the width.
    fn height(&self) -> u32 {
        self.height.unwrap_or(self.width * 3 / 4)
    }
}

fn camera(kind: CameraKind, w: u32, h: u32) -> CameraModel {
    match kind {
        CameraKind::Pinhole => {
            let s = f64::from(w) / 640.0;
            CameraModel::Pinhole(PinholeCamera::new(
                525.0 * s,
                525.0 * s,
                f64::from(w) * 0.5 - 0.5,
                f64::from(h) * 0.5 - 0.5,
                w,
                h,
            ))
        }
        CameraKind::Omni => CameraModel::Unified(UnifiedCamera::catadioptric(w, h)),
    }
}

/// The writer of the output folder: TUM for any camera, the other layouts for pinhole ones.
enum Writer {
    Tum(TumWriter),
    Layout(Box<LayoutWriter>),
}

fn progress(len: usize, what: &str) -> ProgressBar {
    let bar = ProgressBar::new(len as u64);
    if let Ok(style) = ProgressStyle::with_template(
        "{msg} [{elapsed_precise}] {wide_bar} {pos}/{len} ({per_sec}, eta {eta})",
    ) {
        bar.set_style(style);
    }
    bar.set_message(what.to_string());
    bar
}

/// Runs the subcommand.
pub fn run(args: Args) -> Result<()> {
    if !PRESETS.contains(&args.scene.as_str()) {
        bail!(
            "unknown scene '{}' (known: {})",
            args.scene,
            PRESETS.join(", ")
        );
    }
    let kind = TrajectoryKind::from_name(&args.trajectory)?;
    if args.frames == 0 {
        bail!("--frames must be at least 1");
    }
    let base = Arc::new(Scene::preset(&args.scene, args.seed)?);
    let cam = camera(args.camera, args.width, args.height());
    let config = SequenceConfig {
        frames: args.frames,
        fps: args.fps,
        start_time: 0.0,
        sensor: if args.no_noise {
            SensorModel::noiseless()
        } else {
            SensorModel::kinect()
        },
        seed: args.seed,
        exposure_changes: args.exposure_changes,
        motion_blur: args.motion_blur,
        exposure_time: 1.0 / 60.0,
    };
    let trajectory = Trajectory::new(kind, &base, config.duration(), args.seed)?;
    if args.bench {
        return bench(&args, base, cam, trajectory, config);
    }
    let Some(out) = args.out.clone() else {
        bail!("--out DIR is required (or use --bench)");
    };
    let backend = match select_backend(args.backend, args.adapter.as_deref())? {
        ComputeBackend::Cpu => RenderBackend::Cpu,
        ComputeBackend::Gpu(g) => RenderBackend::Gpu(g),
    };
    let sessions = args.sessions.max(1);
    if args.layout != Layout::Tum && sessions > 1 {
        bail!("--sessions > 1 writes moved-object masks, which only --layout tum holds");
    }
    for s in 0..sessions {
        let scene = Arc::new(base.session(s));
        let dir = if sessions > 1 {
            out.join(format!("session_{s:02}"))
        } else {
            out.clone()
        };
        let mut seq = Sequence::new(
            scene.clone(),
            cam,
            trajectory.clone(),
            config.clone(),
            &backend,
        )?;
        let mut writer = match (cam, args.layout) {
            (CameraModel::Pinhole(c), layout) => {
                Writer::Layout(Box::new(LayoutWriter::create(&dir, layout, &c)?))
            }
            (_, Layout::Tum) => Writer::Tum(TumWriter::create(&dir, &cam)?),
            (_, layout) => bail!("--layout {layout} needs --camera pinhole"),
        };
        let bar = progress(args.frames, &format!("session {s}"));
        let started = Instant::now();
        for f in &mut seq {
            let f = f?;
            match &mut writer {
                Writer::Tum(w) => w.write_frame(f.timestamp, &f.world_from_camera, &f.frame)?,
                Writer::Layout(w) => w.write_frame(f.timestamp, &f.world_from_camera, &f.frame)?,
            }
            bar.inc(1);
        }
        bar.finish_and_clear();
        let readme = readme(
            &args,
            &scene,
            &cam,
            &config,
            s,
            seq.renderer().backend_name(),
        );
        let session_txt = format!(
            "session {s}\nchanged_objects {}\n",
            scene
                .changed_objects()
                .iter()
                .map(|i| i.to_string())
                .collect::<Vec<_>>()
                .join(" ")
        );
        let scene_json =
            serde_json::to_string_pretty(scene.params()).context("scene parameters to JSON")?;
        let extra = [
            ("session.txt", session_txt),
            ("scene.json", scene_json + "\n"),
        ];
        match writer {
            Writer::Tum(w) => w.finish(&readme, &extra)?,
            Writer::Layout(w) => w.finish(&readme, &extra)?,
        }
        println!(
            "wrote {} frames to {} in {:.1} s ({})",
            args.frames,
            dir.display(),
            started.elapsed().as_secs_f64(),
            seq.renderer().backend_name()
        );
    }
    Ok(())
}

fn readme(
    args: &Args,
    scene: &Scene,
    cam: &CameraModel,
    config: &SequenceConfig,
    session: u32,
    backend: String,
) -> String {
    let sensor = serde_json::to_string(&config.sensor).unwrap_or_default();
    let camera = serde_json::to_string(cam).unwrap_or_default();
    format!(
        "Synthetic sequence rendered by rgbid synth (exact ground truth).\n\
         \n\
         command: rgbid synth --scene {} --trajectory {} --frames {} --fps {} --camera {:?} \
         --width {} --height {} --seed {}{}{}{} --sessions {} --layout {}\n\
         session: {session} (changed objects: {:?})\n\
         scene: {} ({} primitives, {} objects)\n\
         camera: {camera}\n\
         sensor: {sensor}\n\
         ray casting backend used: {backend} (output does not depend on it beyond f32 rounding)\n\
         \n\
         World frame: z up, floor at z = 0. Ground truth is world_from_camera (camera x right,\n\
         y down, z forward): groundtruth.txt in TUM format for the tum and eth3d layouts, else the\n\
         layout's own pose files. Depth PNGs: 16-bit, 5000 per metre, 0 = no measurement (tum,\n\
         eth3d; 7scenes and scannet: millimetres, replica: 6553.5 per metre).\n\
         masks/ (sessions > 0): 255 where the pixel sees an object moved or added since session 0.\n\
         Available scenes: {}; trajectories: {}.\n",
        args.scene,
        args.trajectory,
        args.frames,
        args.fps,
        args.camera,
        args.width,
        args.height(),
        args.seed,
        if args.no_noise { " --no-noise" } else { "" },
        if args.exposure_changes { " --exposure-changes" } else { "" },
        if args.motion_blur > 1 { format!(" --motion-blur {}", args.motion_blur) } else { String::new() },
        args.sessions,
        args.layout,
        scene.changed_objects(),
        scene.params().name,
        scene.primitive_count(),
        scene.objects().len(),
        PRESETS.join(", "),
        TRAJECTORIES.join(", "),
    )
}

fn bench(
    args: &Args,
    scene: Arc<Scene>,
    cam: CameraModel,
    trajectory: Trajectory,
    config: SequenceConfig,
) -> Result<()> {
    let mut backends = vec![RenderBackend::Cpu];
    if args.backend != BackendChoice::Cpu {
        if let Ok(ComputeBackend::Gpu(g)) =
            select_backend(BackendChoice::Gpu, args.adapter.as_deref())
        {
            backends.push(RenderBackend::Gpu(g));
        } else {
            println!("no GPU adapter: timing the CPU backend only");
        }
    }
    println!(
        "rendering {} frames of {}x{} ({} scene, {} primitives, {} trajectory), sensor model included",
        args.frames,
        args.width,
        args.height(),
        args.scene,
        scene.primitive_count(),
        args.trajectory
    );
    for backend in backends {
        let mut seq = Sequence::new(
            scene.clone(),
            cam,
            trajectory.clone(),
            config.clone(),
            &backend,
        )?;
        let name = seq.renderer().backend_name();
        // One warm-up frame (pipeline compilation on GPUs) outside the timing.
        seq.render_frame(0)?;
        let bar = progress(args.frames, &name);
        let started = Instant::now();
        let mut checksum = 0u64;
        for f in &mut seq {
            let f = f?;
            checksum =
                checksum.wrapping_add(f.frame.rgb.iter().map(|v| u64::from(*v)).sum::<u64>());
            bar.inc(1);
        }
        bar.finish_and_clear();
        let secs = started.elapsed().as_secs_f64();
        println!(
            "{name}: {:.2} s for {} frames ({:.1} ms/frame, {:.1} fps) [checksum {checksum}]",
            secs,
            args.frames,
            secs * 1e3 / args.frames as f64,
            args.frames as f64 / secs
        );
    }
    Ok(())
}
