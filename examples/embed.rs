//! Embedding RGB-ID SLAM in an application with a live camera.
//!
//! A camera thread hands over raw buffers as an RGB-D driver does (8-bit RGB, 16-bit depth in
//! units of 1/5000 m); the main thread turns each into a frame, runs [`Slam`] on it, and
//! prints poses and what the system did (keyframes, loops, graph optimisations) as it
//! happens. Here the camera renders a generated office (1.3 laps of a loop, so the end
//! revisits the start and closes the loop).
//!
//! `cargo run --release --example embed` (it needs only the library:
//! `--no-default-features` works too).

use std::sync::mpsc::{sync_channel, SyncSender};
use std::sync::Arc;

use rgbid::camera::PinholeCamera;
use rgbid::gpu::{select_backend, BackendChoice};
use rgbid::image::{DepthBuffer, ImageBuffer, ImageError, RgbdFrame};
use rgbid::place::Vocabulary;
use rgbid::slam::{Slam, SlamConfig, SlamEvent};
use rgbid::synth::{
    CameraModel, RenderBackend, Scene, Sequence, SequenceConfig, Trajectory, TrajectoryKind,
};

/// What a camera driver delivers.
struct RawFrame {
    /// Seconds.
    timestamp: f64,
    width: usize,
    height: usize,
    /// Interleaved 8-bit RGB, row-major.
    rgb: Vec<u8>,
    /// Depth in units of `1 / depth_factor` metres, 0 = no measurement.
    depth: Vec<u16>,
    depth_factor: f64,
}

/// The frame `Slam` takes, from the driver's buffers (sizes checked; a mismatch names the
/// buffer). The colour is kept in the frame.
fn to_frame(raw: &RawFrame) -> Result<RgbdFrame, ImageError> {
    RgbdFrame::from_buffers(
        raw.timestamp,
        raw.width,
        raw.height,
        ImageBuffer::Rgb(&raw.rgb),
        DepthBuffer::U16 {
            data: &raw.depth,
            factor: raw.depth_factor,
        },
    )
}

/// The camera: renders `frames` frames and sends them until the receiver hangs up.
fn camera(cam: PinholeCamera, frames: usize, tx: SyncSender<RawFrame>) -> anyhow::Result<()> {
    let scene = Arc::new(Scene::preset("office", 7)?);
    let config = SequenceConfig {
        frames,
        seed: 7,
        ..Default::default()
    };
    let lap_seconds = config.duration() / 1.3;
    let trajectory = Trajectory::new(TrajectoryKind::Loop, &scene, lap_seconds, 7)?;
    let mut seq = Sequence::new(
        scene,
        CameraModel::Pinhole(cam),
        trajectory,
        config,
        &RenderBackend::Cpu,
    )?;
    for i in 0..frames {
        let f = seq.render_frame(i)?;
        let raw = RawFrame {
            timestamp: f.timestamp,
            width: cam.width as usize,
            height: cam.height as usize,
            depth: f.frame.depth_u16(),
            rgb: f.frame.rgb,
            depth_factor: rgbid::synth::DEPTH_FACTOR,
        };
        if tx.send(raw).is_err() {
            break;
        }
    }
    Ok(())
}

fn print_event(event: &SlamEvent) {
    match event {
        SlamEvent::KeyframeCreated {
            id, frame_index, ..
        } => println!("  keyframe {id} created at frame {frame_index}"),
        SlamEvent::KeyframeDescribed(d) => println!(
            "  keyframe {} described: {} superjuts, {} ORB keypoints",
            d.id,
            d.neg_entropy.len(),
            d.keypoints.len()
        ),
        SlamEvent::LoopChecked(l) => println!(
            "  loop {} -> {}: {} inliers, {}",
            l.query, l.candidate, l.inliers, l.verdict
        ),
        SlamEvent::GraphOptimised {
            world_from_keyframe,
            loops,
            ..
        } => println!(
            "  pose graph optimised: {} keyframes, {loops} loops",
            world_from_keyframe.len()
        ),
        SlamEvent::Lost { frame_index, .. } => println!("  lost at frame {frame_index}"),
        SlamEvent::Relocalised {
            frame_index,
            keyframe,
            ..
        } => println!("  relocalised at frame {frame_index} against keyframe {keyframe}"),
        other => println!("  {other:?}"),
    }
}

fn main() -> anyhow::Result<()> {
    let (width, height, frames) = (256, 192, 300);
    let f = 525.0 * f64::from(width) / 640.0;
    let cam = PinholeCamera::new(
        f,
        f,
        f64::from(width) / 2.0 - 0.5,
        f64::from(height) / 2.0 - 0.5,
        width,
        height,
    );
    let (tx, rx) = sync_channel(4);
    let camera = std::thread::spawn(move || camera(cam, frames, tx));

    let backend = select_backend(BackendChoice::Auto, None)?;
    let vocabulary = Vocabulary::embedded_default()?;
    let mut slam = Slam::new(SlamConfig::default(), cam, &backend, vocabulary, None)?;
    let events = slam.events();
    for raw in rx {
        let report = slam.process(&to_frame(&raw)?)?;
        if report.record.index % 30 == 0 {
            match report.world_from_camera {
                Some(p) => println!(
                    "frame {:3} t {:5.2} s  position {:+.3} {:+.3} {:+.3} m",
                    report.record.index,
                    raw.timestamp,
                    p.translation.x,
                    p.translation.y,
                    p.translation.z
                ),
                None => println!("frame {:3} lost", report.record.index),
            }
        }
        events.try_iter().for_each(|e| print_event(&e));
    }
    camera
        .join()
        .map_err(|_| anyhow::anyhow!("the camera thread panicked"))??;

    let result = slam.finish()?;
    // What the back-end did after the last frame, until the stream ends.
    events.iter().for_each(|e| print_event(&e));
    let accepted = result
        .loops
        .iter()
        .filter(|l| l.verdict.is_accepted())
        .count();
    println!(
        "{} frames, {} keyframes, {accepted} loops accepted; events dropped: {:?}",
        result.frames.len(),
        result.keyframes().len(),
        events.dropped()
    );
    Ok(())
}
