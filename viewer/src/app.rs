//! The egui application: controls, image panels, plots and the 3D view.

use std::collections::VecDeque;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use anyhow::{Context, Result};
use egui::{Color32, PointerButton, RichText, Sense, TextureHandle, TextureOptions, Vec2};
use egui_plot::{HLine, Legend, Line, Plot, PlotPoints};
use rgbid::gpu::BackendChoice;
use rgbid::io::trajectory::write_tum;
use rgbid::trajectory::TimedPose;

use crate::images;
use crate::output::{known, load_map, load_output};
use crate::scene3d::{OrbitCamera, SceneCallback};
use crate::source::{SourceSpec, SynthOptions};
use crate::state::{colours, PointColours, ViewerState};
use crate::worker::{Command, RunConfig, Worker};
use rgbid::io::run_folder::FrameRow;

/// Textures of the image panels, re-uploaded when the panels' version changes.
#[derive(Default)]
struct Textures {
    version: Option<u64>,
    intensity: Option<TextureHandle>,
    inverse_depth: Option<TextureHandle>,
    superjuts: Option<TextureHandle>,
    neg_entropy: Option<TextureHandle>,
    residual_photo: Option<TextureHandle>,
    residual_geo: Option<TextureHandle>,
    weight_photo: Option<TextureHandle>,
    weight_geo: Option<TextureHandle>,
    keypoints: Option<TextureHandle>,
    loop_accepted: Option<TextureHandle>,
    loop_rejected: Option<TextureHandle>,
}

/// Pace choices (multiples of 30 fps; 0 = as fast as possible).
pub const SPEEDS: [(f64, &str); 5] = [
    (0.25, "0.25x"),
    (0.5, "0.5x"),
    (1.0, "1x (30 fps)"),
    (2.0, "2x"),
    (0.0, "max"),
];

/// What the 3D view draws of the map.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Surface {
    /// The keyframe points (live) or the model's points (finished).
    Points,
    /// The TSDF mesh, when the run has one (points otherwise).
    Mesh,
}

/// The viewer application.
pub struct ViewerApp {
    /// What is shown.
    pub state: ViewerState,
    /// The running SLAM thread, if any.
    pub worker: Option<Worker>,
    /// Settings of the current / next run (None when showing a folder or map).
    pub run_config: Option<RunConfig>,
    /// Whether the run is playing.
    pub playing: bool,
    /// Pace (see [`SPEEDS`]).
    pub speed: f64,
    /// 3D camera.
    pub camera: OrbitCamera,
    /// Keep the 3D camera's target on the current pose.
    pub follow: bool,
    /// Fixed inverse-depth colour scale (1/m), or automatic.
    pub inverse_depth_max: Option<f32>,
    /// Folder for exports (trajectory, PLY, screenshots).
    pub export_dir: PathBuf,
    /// Path typed into the "open" field.
    pub open_path: String,
    /// Last message for the user (exports, errors of opening).
    pub message: String,
    /// Whether a wgpu renderer for the 3D view is installed.
    pub has_3d: bool,
    /// Show the UI frame time in the status line (off in snapshot tests).
    pub show_timing: bool,
    /// Most points drawn per frame in the 3D view (`None` = all). Points are stored in an
    /// interleaved order, so a budget draws a uniform subsample.
    pub point_budget: Option<u32>,
    /// Points or mesh in the 3D view; `None` = the mesh when there is one, else the points.
    pub surface: Option<Surface>,
    framed: bool,
    textures: Textures,
    frame_ms: VecDeque<f64>,
    last_ui: Option<Instant>,
    screenshot_message: Arc<Mutex<Option<String>>>,
    /// The frame-time measurement of [`FrameBench`], when asked for.
    pub frame_bench: Option<FrameBench>,
}

/// A frame-time measurement in the window: once the run has finished (or at once when showing
/// a folder or map), the 3D camera orbits a little every frame for `frames` frames (so the
/// whole UI and the 3D view are drawn again each time); then one line with the median and
/// 95th-percentile time between frames goes to stdout, followed by a line `ready`. Enabled by
/// the environment variable `RGBID_VIEWER_FRAME_BENCH=FRAMES` (see [`FrameBench::from_env`]).
#[derive(Clone, Debug, Default)]
pub struct FrameBench {
    /// Frames to measure.
    pub frames: usize,
    /// Times between frames so far, milliseconds.
    pub times_ms: Vec<f64>,
    /// Median UI frame time of the live run (before the measurement), milliseconds.
    pub live_ms: Option<f64>,
    last: Option<Instant>,
    done: bool,
}

impl FrameBench {
    /// Environment variable that enables the measurement (a number of frames).
    pub const ENV: &'static str = "RGBID_VIEWER_FRAME_BENCH";

    /// The measurement asked for by [`Self::ENV`], if set to a positive number.
    pub fn from_env() -> Option<Self> {
        let frames: usize = std::env::var(Self::ENV).ok()?.trim().parse().ok()?;
        (frames > 0).then(|| FrameBench {
            frames,
            ..Default::default()
        })
    }

    /// Whether the measurement has finished and was reported.
    pub fn done(&self) -> bool {
        self.done
    }
}

impl ViewerApp {
    /// An app showing `state`; with `run_config` a SLAM run starts at once.
    pub fn new(state: ViewerState, run_config: Option<RunConfig>) -> Self {
        let playing = run_config.as_ref().is_some_and(|c| c.autoplay);
        let mut app = ViewerApp {
            state,
            worker: None,
            run_config,
            playing,
            speed: 1.0,
            camera: OrbitCamera::default(),
            follow: false,
            inverse_depth_max: None,
            export_dir: PathBuf::from("viewer-export"),
            open_path: String::new(),
            message: String::new(),
            has_3d: false,
            show_timing: true,
            point_budget: None,
            surface: None,
            framed: false,
            textures: Textures::default(),
            frame_ms: VecDeque::new(),
            last_ui: None,
            screenshot_message: Arc::new(Mutex::new(None)),
            frame_bench: None,
        };
        if app.run_config.is_some() {
            app.restart();
        }
        app
    }

    /// (Re)starts the SLAM run with the current settings.
    pub fn restart(&mut self) {
        self.worker = None; // joins the old thread
        self.replace_state(ViewerState::default());
        let Some(mut cfg) = self.run_config.clone() else {
            return;
        };
        cfg.autoplay = self.playing;
        match Worker::spawn(cfg) {
            Ok(w) => {
                w.send(Command::Speed(self.speed));
                self.worker = Some(w);
            }
            Err(e) => self.state.error = Some(format!("{e:#}")),
        }
    }

    /// Opens a path: an `rgbid slam` output folder (has trajectory.txt), a saved map file, or
    /// a TUM RGB-D folder (starts SLAM).
    pub fn open(&mut self, path: &Path) -> Result<()> {
        if path.is_dir() && rgbid::io::run_folder::RunFolder::is_run_folder(path) {
            let folder = load_output(path)?;
            self.worker = None;
            self.run_config = None;
            self.replace_state(ViewerState::from_output(folder));
        } else if path.is_file() {
            let run = load_map(path, rgbid::slam::ModelParams::default().voxel)?;
            self.worker = None;
            self.run_config = None;
            self.replace_state(ViewerState::from_run(run));
        } else if path.is_dir() {
            let backend = self
                .run_config
                .as_ref()
                .map_or(BackendChoice::Auto, |c| c.backend);
            let mut cfg = RunConfig::new(SourceSpec::Tum {
                dir: path.to_path_buf(),
                format: None,
                camera: None,
                max_frames: None,
            });
            cfg.backend = backend;
            self.run_config = Some(cfg);
            self.playing = true;
            self.restart();
        } else {
            anyhow::bail!("{} does not exist", path.display());
        }
        Ok(())
    }

    /// Shows `state` instead of the current one, keeping the colouring chosen.
    fn replace_state(&mut self, mut state: ViewerState) {
        state.set_point_colours(self.state.point_colours());
        self.state = state;
        self.framed = false;
    }

    /// Whether the 3D view draws the mesh (chosen, or by default when the run has one).
    pub fn shows_mesh(&self) -> bool {
        self.state.geometry.mesh.is_some() && self.surface != Some(Surface::Points)
    }

    /// Applies pending messages of the SLAM thread (at most a bounded number per call).
    /// Returns whether anything changed.
    pub fn poll(&mut self) -> bool {
        let Some(w) = &self.worker else {
            return false;
        };
        let mut changed = false;
        for _ in 0..64 {
            match w.updates.try_recv() {
                Ok(u) => {
                    self.state.apply(u);
                    changed = true;
                }
                Err(_) => break,
            }
        }
        changed
    }

    /// Blocks until the run has finished (or failed), applying every message (tests, scripts).
    pub fn wait_until_finished(&mut self) {
        let Some(w) = &self.worker else {
            return;
        };
        while self.state.finished.is_none() && self.state.error.is_none() {
            match w.updates.recv() {
                Ok(u) => self.state.apply(u),
                Err(_) => break,
            }
        }
    }

    /// Sends the current pace to the SLAM thread.
    pub fn send_speed(&self) {
        self.send(Command::Speed(self.speed));
    }

    fn send(&self, c: Command) {
        if let Some(w) = &self.worker {
            w.send(c);
        }
    }

    /// Median UI frame time over the last frames, milliseconds.
    pub fn median_frame_ms(&self) -> Option<f64> {
        let mut v: Vec<f64> = self.frame_ms.iter().copied().collect();
        if v.is_empty() {
            return None;
        }
        v.sort_by(f64::total_cmp);
        Some(v[v.len() / 2])
    }

    /// The whole UI.
    pub fn show(&mut self, ui: &mut egui::Ui) {
        let now = Instant::now();
        if let Some(t) = self.last_ui.replace(now) {
            self.frame_ms.push_back((now - t).as_secs_f64() * 1e3);
            if self.frame_ms.len() > 120 {
                self.frame_ms.pop_front();
            }
        }
        if let Some(m) = self
            .screenshot_message
            .lock()
            .ok()
            .and_then(|mut m| m.take())
        {
            self.message = m;
        }
        egui::Panel::top("controls").show(ui, |ui| self.controls_ui(ui));
        egui::Panel::left("images")
            .resizable(true)
            .default_size(340.0)
            .show(ui, |ui| {
                egui::ScrollArea::vertical().show(ui, |ui| self.images_ui(ui));
            });
        egui::Panel::bottom("plots")
            .resizable(true)
            .default_size(230.0)
            .show(ui, |ui| self.plots_ui(ui));
        egui::CentralPanel::default().show(ui, |ui| self.scene_ui(ui));
    }

    /// Play / pause / step, speed, backend, parameters, open and export.
    pub fn controls_ui(&mut self, ui: &mut egui::Ui) {
        ui.horizontal_wrapped(|ui| {
            let live = self.worker.is_some() && self.state.finished.is_none();
            ui.add_enabled_ui(live, |ui| {
                if ui
                    .button(if self.playing { "Pause" } else { "Play" })
                    .clicked()
                {
                    self.playing = !self.playing;
                    self.send(if self.playing {
                        Command::Play
                    } else {
                        Command::Pause
                    });
                }
                if ui.button("Step").clicked() {
                    self.playing = false;
                    self.send(Command::Step);
                }
                if ui
                    .button("Finish")
                    .on_hover_text("stop feeding frames, optimise, build the model")
                    .clicked()
                {
                    self.send(Command::Finish);
                }
            });
            let label = SPEEDS
                .iter()
                .find(|s| s.0 == self.speed)
                .map_or("?", |s| s.1);
            let before = self.speed;
            egui::ComboBox::from_id_salt("speed")
                .selected_text(label)
                .show_ui(ui, |ui| {
                    for (v, name) in SPEEDS {
                        ui.selectable_value(&mut self.speed, v, name);
                    }
                });
            if self.speed != before {
                self.send(Command::Speed(self.speed));
            }
            ui.separator();
            if let Some(cfg) = &mut self.run_config {
                egui::ComboBox::from_id_salt("backend")
                    .selected_text(format!("backend: {:?}", cfg.backend).to_lowercase())
                    .show_ui(ui, |ui| {
                        ui.selectable_value(&mut cfg.backend, BackendChoice::Auto, "auto");
                        ui.selectable_value(&mut cfg.backend, BackendChoice::Gpu, "gpu");
                        ui.selectable_value(&mut cfg.backend, BackendChoice::Cpu, "cpu");
                    });
                ui.add(
                    egui::DragValue::new(&mut cfg.keyframe_covisibility)
                        .range(0.3..=0.95)
                        .speed(0.01)
                        .prefix("keyframe covis "),
                );
                ui.checkbox(&mut cfg.masks, "masks");
                ui.checkbox(&mut cfg.segment_keyframes, "superjut panels");
                if ui
                    .button("Restart")
                    .on_hover_text("apply backend and parameters")
                    .clicked()
                {
                    self.restart();
                }
            }
        });
        ui.horizontal_wrapped(|ui| {
            ui.add(
                egui::TextEdit::singleline(&mut self.open_path)
                    .hint_text("TUM folder, output folder or map file")
                    .desired_width(260.0),
            );
            if ui.button("Open").clicked() {
                let p = PathBuf::from(self.open_path.trim());
                if let Err(e) = self.open(&p) {
                    self.message = format!("open: {e:#}");
                }
            }
            if ui
                .button(format!("synth {}", SynthOptions::DEFAULT_SPEC))
                .clicked()
            {
                let spec = SynthOptions::default().spec_of(SynthOptions::DEFAULT_SPEC, 0, None);
                let mut cfg = match spec {
                    Ok(spec) => RunConfig::new(spec),
                    Err(e) => {
                        self.message = format!("synth: {e}");
                        return;
                    }
                };
                if let Some(old) = &self.run_config {
                    cfg.backend = old.backend;
                }
                self.run_config = Some(cfg);
                self.playing = true;
                self.restart();
            }
            ui.separator();
            ui.label("export to");
            let mut dir = self.export_dir.display().to_string();
            if ui
                .add(egui::TextEdit::singleline(&mut dir).desired_width(120.0))
                .changed()
            {
                self.export_dir = PathBuf::from(dir);
            }
            if ui.button("trajectory").clicked() {
                self.message = report("trajectory", self.export_trajectory());
            }
            if ui.button("PLY").clicked() {
                self.message = report("PLY", self.export_ply());
            }
            if ui.button("screenshot").clicked() {
                self.request_screenshot(ui.ctx());
            }
        });
        ui.horizontal_wrapped(|ui| {
            ui.label(self.status_text());
            if let Some(e) = &self.state.error {
                ui.colored_label(Color32::LIGHT_RED, format!("error: {e}"));
            }
            if !self.message.is_empty() {
                ui.label(RichText::new(&self.message).italics());
            }
        });
    }

    /// One line of status.
    pub fn status_text(&self) -> String {
        let s = &self.state;
        let frames = s
            .start
            .as_ref()
            .and_then(|i| i.frames)
            .map_or(String::new(), |n| format!("/{n}"));
        let frame = s
            .last_frame
            .map_or("-".to_string(), |f| format!("{}{frames}", f + 1));
        let status = if s.finished.is_some() {
            "finished".to_string()
        } else {
            s.last_status
                .map_or("-".to_string(), |st| format!("{st:?}"))
        };
        let backend = s
            .start
            .as_ref()
            .map_or(String::new(), |i| format!(" | {}", i.backend));
        let ui_ms = self
            .median_frame_ms()
            .filter(|_| self.show_timing)
            .map_or(String::new(), |m| format!(" | UI {m:.1} ms"));
        let live = s.live.map_or(String::new(), |c| {
            let recorded = match c.recorded {
                Some(n) => format!(", {n} recorded"),
                None if c.finished => String::new(),
                None if self.records() => ", recording".to_string(),
                None => String::new(),
            };
            format!(
                " | live: {} received, {} dropped{recorded}{}",
                c.received,
                c.dropped,
                if c.finished { " (camera stopped)" } else { "" }
            )
        });
        let mesh = s.geometry.mesh.as_ref().map_or(String::new(), |m| {
            format!(" | mesh {} triangles", m.triangles.len())
        });
        format!(
            "frame {frame} | {status} | {} keyframes | {} loops | {} points{mesh}{live}{backend}{ui_ms}",
            s.keyframe_count,
            s.loop_count,
            s.point_count()
        )
    }

    /// Whether the current run records its live input.
    fn records(&self) -> bool {
        matches!(
            &self.run_config,
            Some(RunConfig {
                source: crate::worker::RunSource::Live { options, .. },
                ..
            }) if options.record.is_some()
        )
    }

    fn refresh_textures(&mut self, ctx: &egui::Context) {
        let p = &self.state.panels;
        if self.textures.version == Some(p.version) {
            return;
        }
        self.textures.version = Some(p.version);
        let opts = TextureOptions::NEAREST;
        let set =
            |slot: &mut Option<TextureHandle>, name: &str, img: Option<egui::ColorImage>| match (
                slot.as_mut(),
                img,
            ) {
                (Some(t), Some(img)) => t.set(img, opts),
                (None, Some(img)) => *slot = Some(ctx.load_texture(name, img, opts)),
                (_, None) => *slot = None,
            };
        set(
            &mut self.textures.intensity,
            "intensity",
            p.intensity.as_ref().map(images::intensity_image),
        );
        set(
            &mut self.textures.inverse_depth,
            "inverse depth",
            p.inverse_depth
                .as_ref()
                .map(|i| images::inverse_depth_image(i, self.inverse_depth_max)),
        );
        set(
            &mut self.textures.superjuts,
            "superjuts",
            p.superjuts
                .as_ref()
                .and_then(|(w, h, rgb)| images::rgb_image(*w, *h, rgb)),
        );
        set(
            &mut self.textures.neg_entropy,
            "neg-entropy",
            p.neg_entropy
                .as_ref()
                .map(|n| images::neg_entropy_overlay(n, p.keyframe_intensity.as_ref())),
        );
        set(
            &mut self.textures.keypoints,
            "keypoints",
            p.keyframe_intensity
                .as_ref()
                .filter(|_| !p.keypoints.is_empty())
                .map(|i| images::keypoints_overlay(i, &p.keypoints)),
        );
        let loop_image = |l: &crate::worker::LoopUpdate| match (&l.query_image, &l.candidate_image)
        {
            (Some(q), Some(c)) => Some(images::loop_matches_image(q, c, &l.matches)),
            _ => None,
        };
        set(
            &mut self.textures.loop_accepted,
            "loop accepted",
            p.loop_accepted.as_ref().and_then(loop_image),
        );
        set(
            &mut self.textures.loop_rejected,
            "loop rejected",
            p.loop_rejected.as_ref().and_then(loop_image),
        );
        let r = p.residuals.as_ref();
        set(
            &mut self.textures.residual_photo,
            "photometric residual",
            r.map(|r| images::signed_image(&r.photometric, None)),
        );
        set(
            &mut self.textures.residual_geo,
            "geometric residual",
            r.map(|r| images::signed_image(&r.geometric, None)),
        );
        set(
            &mut self.textures.weight_photo,
            "photometric weight",
            r.map(|r| images::weight_image(&r.photometric_weight)),
        );
        set(
            &mut self.textures.weight_geo,
            "geometric weight",
            r.map(|r| images::weight_image(&r.geometric_weight)),
        );
    }

    /// The image panels, two per row: the frame (intensity, inverse depth), its residuals
    /// against the odometry reference and their IRLS weights, the latest keyframe's superjuts
    /// and neg-entropy, its ORB keypoints, and the latest accepted and rejected loops with
    /// their inlier matches.
    pub fn images_ui(&mut self, ui: &mut egui::Ui) {
        self.refresh_textures(ui.ctx());
        let width = ((ui.available_width() - 8.0) / 2.0).max(64.0);
        let show = |ui: &mut egui::Ui, title: &str, tex: &Option<TextureHandle>| {
            ui.vertical(|ui| {
                ui.set_width(width);
                ui.label(RichText::new(title).strong());
                match tex {
                    Some(t) => image_at_width(ui, t, width),
                    None => {
                        ui.label("(none yet)");
                    }
                }
            });
        };
        let t = &self.textures;
        let rows: [&[(&str, &Option<TextureHandle>)]; 5] = [
            &[
                ("intensity", &t.intensity),
                ("inverse depth (near = red)", &t.inverse_depth),
            ],
            &[
                ("photometric residual (+ red, - blue)", &t.residual_photo),
                ("geometric residual", &t.residual_geo),
            ],
            &[
                ("photometric IRLS weight (0 blue, 1 red)", &t.weight_photo),
                ("geometric IRLS weight", &t.weight_geo),
            ],
            &[
                ("superjuts (latest keyframe)", &t.superjuts),
                ("neg-entropy (latest keyframe)", &t.neg_entropy),
            ],
            &[(
                "ORB keypoints (latest keyframe; green: kept by the neg-entropy mask)",
                &t.keypoints,
            )],
        ];
        egui::ScrollArea::vertical().show(ui, |ui| {
            for row in rows {
                ui.horizontal_top(|ui| {
                    for &(title, tex) in row {
                        show(ui, title, tex);
                    }
                });
            }
            self.loop_panels(ui, width);
        });
    }

    /// The loop panels, side by side and `width` points wide each: the latest accepted and
    /// the latest rejected loop, each as the query keyframe above the candidate with a line
    /// per inlier match, and a caption (ids, inliers, verdict); a placeholder before any loop.
    pub fn loops_ui(&mut self, ui: &mut egui::Ui) {
        self.refresh_textures(ui.ctx());
        let width = ((ui.available_width() - 8.0) / 2.0).max(64.0);
        self.loop_panels(ui, width);
    }

    /// [`Self::loops_ui`] with the textures refreshed.
    fn loop_panels(&self, ui: &mut egui::Ui, width: f32) {
        let t = &self.textures;
        let p = &self.state.panels;
        // Without a loop: why (a finished folder or map), or that none was found yet.
        let none = p
            .loop_note
            .as_deref()
            .unwrap_or("(no loop yet: loops appear when the camera revisits a place)");
        let loops = [
            (
                "loop matches: latest accepted",
                &p.loop_accepted,
                &t.loop_accepted,
                none,
            ),
            (
                "latest rejected loop",
                &p.loop_rejected,
                &t.loop_rejected,
                if p.loop_note.is_some() {
                    "(none)"
                } else {
                    "(none yet: a verified loop the dense checks reject shows here)"
                },
            ),
        ];
        let show_loop = |ui: &mut egui::Ui,
                         title: &str,
                         l: &Option<crate::worker::LoopUpdate>,
                         tex: &Option<TextureHandle>,
                         none: &str| {
            ui.vertical(|ui| {
                ui.set_width(width);
                ui.label(RichText::new(title).strong());
                let Some(l) = l else {
                    ui.label(none);
                    return;
                };
                ui.label(loop_caption(l));
                match tex {
                    Some(t) => image_at_width(ui, t, width),
                    None => {
                        ui.label("(keyframe images of this loop are not available)");
                    }
                }
            });
        };
        ui.horizontal_top(|ui| {
            for (title, l, tex, none) in loops {
                show_loop(ui, title, l, tex, none);
            }
        });
    }

    /// The plots: time per stage, covisibility, robust scales, condition number, position
    /// error.
    pub fn plots_ui(&mut self, ui: &mut egui::Ui) {
        let stages = &self.state.stages;
        let height = (ui.available_height() - 24.0).max(80.0);
        // Unknown values (NaN: lost frames, the first frame's diagnostics) are left out; the
        // tessellator must not see them.
        let series = |f: fn(&FrameRow) -> f64| -> PlotPoints<'static> {
            stages
                .iter()
                .map(|r| [r.index as f64, f(r)])
                .filter(|p| p[1].is_finite())
                .collect()
        };
        let has_error = !self.state.position_error.is_empty();
        let n = if has_error { 5 } else { 4 };
        ui.columns(n, |cols| {
            cols[0].label(RichText::new("time per stage (ms)").strong());
            Plot::new("stage_times")
                .height(height)
                .legend(Legend::default())
                .x_axis_label("frame")
                .show(&mut cols[0], |p| {
                    p.line(Line::new("front-end", series(|r| r.frontend_ms)));
                    p.line(Line::new("pyramid", series(|r| r.pyramid_ms)));
                    p.line(Line::new("scale", series(|r| r.scale_ms)));
                    p.line(Line::new("reduce", series(|r| r.reduce_ms)));
                    p.line(Line::new("solve", series(|r| r.solve_ms)));
                    p.line(Line::new("covisibility", series(|r| r.covisibility_ms)));
                    p.line(Line::new("fusion", series(|r| r.fusion_ms)));
                });
            cols[1].label(RichText::new("covisibility").strong());
            Plot::new("covisibility")
                .height(height)
                .legend(Legend::default())
                .x_axis_label("frame")
                .include_y(0.0)
                .include_y(1.0)
                .show(&mut cols[1], |p| {
                    p.line(Line::new("reference", series(|r| r.covisibility)));
                    p.line(Line::new("keyframe", series(|r| r.keyframe_covisibility)));
                    let defaults = rgbid::slam::SlamConfig::default();
                    if let Some(t) = defaults.odometry.reference_switch {
                        p.hline(HLine::new(format!("reference switch {t}"), t));
                    }
                    let t = defaults.keyframe_covisibility;
                    p.hline(HLine::new(format!("keyframe switch {t}"), t));
                });
            cols[2].label(RichText::new("robust estimator (finest level)").strong());
            Plot::new("robust")
                .height(height)
                .legend(Legend::default())
                .x_axis_label("frame")
                .include_y(0.0)
                .show(&mut cols[2], |p| {
                    p.line(Line::new("sigma_I", series(|r| known(r.sigma_photo))));
                    p.line(Line::new(
                        "sigma_W x1000 (1/m)",
                        series(|r| 1e3 * known(r.sigma_geo)),
                    ));
                    p.line(Line::new("nu", series(|r| known(r.nu))));
                });
            cols[3].label(RichText::new("Hessian condition (log10)").strong());
            Plot::new("condition")
                .height(height)
                .legend(Legend::default())
                .x_axis_label("frame")
                .show(&mut cols[3], |p| {
                    p.line(Line::new(
                        "log10 cond",
                        series(|r| known(r.condition_number).log10()),
                    ));
                });
            if has_error {
                cols[4].label(RichText::new("position error vs ground truth (m)").strong());
                let pts: PlotPoints<'static> = self.state.position_error.iter().copied().collect();
                Plot::new("position_error")
                    .height(height)
                    .legend(Legend::default())
                    .x_axis_label("frame")
                    .include_y(0.0)
                    .show(&mut cols[4], |p| {
                        p.line(Line::new("first-pose aligned", pts));
                    });
            }
        });
    }

    /// The 3D view (wgpu paint callback) with orbit / pan / zoom and follow.
    pub fn scene_ui(&mut self, ui: &mut egui::Ui) {
        self.state.rebuild_geometry();
        if !self.framed {
            if let Some(b) = self.state.geometry.robust_bounds() {
                self.camera.frame_bounds(b);
                self.framed = true;
            }
        }
        ui.horizontal(|ui| {
            ui.checkbox(&mut self.follow, "follow camera");
            if ui.button("frame all").clicked() {
                if let Some(b) = self.state.geometry.robust_bounds() {
                    self.camera.frame_bounds(b);
                }
            }
            let mut limited = self.point_budget.is_some();
            if ui
                .checkbox(&mut limited, "point budget")
                .on_hover_text("draw a uniform subsample (for software renderers such as lavapipe)")
                .changed()
            {
                self.point_budget = limited.then_some(crate::scene3d::SOFTWARE_POINT_BUDGET);
            }
            if let Some(b) = &mut self.point_budget {
                ui.add(
                    egui::DragValue::new(b)
                        .range(1_000..=100_000_000)
                        .speed(1000.0),
                );
            }
            let has_colour = self.state.has_colour();
            let mut c = self.state.point_colours();
            ui.add_enabled_ui(has_colour, |ui| {
                ui.selectable_value(&mut c, PointColours::Colour, "colour")
                    .on_disabled_hover_text("the run has no colour images");
            });
            ui.selectable_value(&mut c, PointColours::Intensity, "intensity");
            self.state.set_point_colours(c);
            if self.state.geometry.mesh.is_some() {
                ui.separator();
                let mut surface = if self.shows_mesh() {
                    Surface::Mesh
                } else {
                    Surface::Points
                };
                let before = surface;
                ui.selectable_value(&mut surface, Surface::Points, "points");
                ui.selectable_value(&mut surface, Surface::Mesh, "mesh");
                if surface != before {
                    self.surface = Some(surface);
                }
            }
            ui.label("drag: orbit | right/middle drag: pan | scroll: zoom");
            ui.colored_label(rgb(colours::ESTIMATE), "estimate");
            ui.colored_label(rgb(colours::GROUND_TRUTH), "ground truth");
            ui.colored_label(rgb(colours::KEYFRAME), "keyframes");
            ui.colored_label(rgb(colours::LOOP), "loops");
        });
        // A colouring chosen above shows in this frame.
        self.state.rebuild_geometry();
        let (rect, response) = ui.allocate_exact_size(ui.available_size(), Sense::click_and_drag());
        if response.dragged_by(PointerButton::Primary) {
            let d = response.drag_delta();
            self.camera.orbit(d.x, d.y);
        }
        if response.dragged_by(PointerButton::Secondary)
            || response.dragged_by(PointerButton::Middle)
        {
            let d = response.drag_delta();
            self.camera.pan(d.x, d.y, rect.height());
        }
        if response.hovered() {
            let scroll = ui.input(|i| i.smooth_scroll_delta.y);
            if scroll != 0.0 {
                self.camera.zoom((-scroll * 0.002).exp());
            }
        }
        if response.double_clicked() {
            if let Some(b) = self.state.geometry.robust_bounds() {
                self.camera.frame_bounds(b);
            }
        }
        if self.follow {
            if let Some(p) = self.state.latest_position() {
                self.camera.target = glam::Vec3::new(p.x as f32, p.y as f32, p.z as f32);
            }
        }
        if !self.has_3d {
            ui.painter().text(
                rect.center(),
                egui::Align2::CENTER_CENTER,
                "3D view needs the wgpu renderer",
                egui::FontId::proportional(16.0),
                Color32::GRAY,
            );
            return;
        }
        let ppp = ui.ctx().pixels_per_point();
        let size_px = [
            (rect.width() * ppp).round().max(1.0) as u32,
            (rect.height() * ppp).round().max(1.0) as u32,
        ];
        let cb = SceneCallback {
            geometry: self.state.geometry.clone(),
            clip_from_world: self
                .camera
                .clip_from_world(rect.width() / rect.height().max(1.0)),
            size_px,
            background: [0.07, 0.07, 0.09],
            point_budget: self.point_budget.unwrap_or(u32::MAX),
            show_points: !self.shows_mesh(),
            show_mesh: self.shows_mesh(),
        };
        ui.painter()
            .add(egui_wgpu::Callback::new_paint_callback(rect, cb));
    }

    /// Writes the trajectory (final if finished, else live) as TUM text.
    pub fn export_trajectory(&self) -> Result<PathBuf> {
        std::fs::create_dir_all(&self.export_dir)
            .with_context(|| format!("creating {}", self.export_dir.display()))?;
        let traj: &[TimedPose] = match &self.state.finished {
            Some(r) => &r.trajectory,
            None => &self.state.live_trajectory,
        };
        let p = self.export_dir.join("trajectory.txt");
        write_tum(&p, traj)?;
        Ok(p)
    }

    /// Writes the model (final if finished, else the live keyframe points) as PLY.
    pub fn export_ply(&self) -> Result<PathBuf> {
        std::fs::create_dir_all(&self.export_dir)
            .with_context(|| format!("creating {}", self.export_dir.display()))?;
        let pts: Vec<(glam::DVec3, [u8; 3])> = match &self.state.finished {
            Some(r) => r.model.clone(),
            None => self
                .state
                .live_keyframes
                .iter()
                .flat_map(|k| k.1.iter().copied())
                .collect(),
        };
        let p = self.export_dir.join("model.ply");
        rgbid::io::ply::write_ply(&p, &pts)?;
        Ok(p)
    }

    fn request_screenshot(&self, ctx: &egui::Context) {
        let dir = self.export_dir.clone();
        let slot = self.screenshot_message.clone();
        let ctx2 = ctx.clone();
        ctx.request_screenshot(move |img| {
            let msg = report("screenshot", save_colour_image(&dir, &img));
            if let Ok(mut s) = slot.lock() {
                *s = Some(msg);
            }
            ctx2.request_repaint();
        });
    }
}

/// Caption of a loop panel: ids, inliers, verdict (the images are stacked: query on top).
pub fn loop_caption(l: &crate::worker::LoopUpdate) -> String {
    let kind = if l.relocalisation {
        "relocalised frame, kf"
    } else {
        "query kf"
    };
    let verdict = if l.accepted {
        "accepted".to_string()
    } else {
        format!("rejected: {}", l.reason)
    };
    let matches = if l.matches.is_empty() {
        " (no matches recorded)"
    } else {
        ""
    };
    format!(
        "{kind} {} (top) / candidate kf {} (bottom), {} inliers{matches}, {verdict}",
        l.query, l.candidate, l.inliers
    )
}

fn rgb(c: [u8; 4]) -> Color32 {
    Color32::from_rgb(c[0], c[1], c[2])
}

fn report(what: &str, r: Result<PathBuf>) -> String {
    match r {
        Ok(p) => format!("{what} saved to {}", p.display()),
        Err(e) => format!("{what}: {e:#}"),
    }
}

/// Saves an egui colour image as PNG in `dir` (name with a time stamp).
pub fn save_colour_image(dir: &Path, img: &egui::ColorImage) -> Result<PathBuf> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let secs = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_millis());
    let p = dir.join(format!("screenshot-{secs}.png"));
    let [w, h] = img.size;
    let bytes: Vec<u8> = img.pixels.iter().flat_map(|c| c.to_array()).collect();
    let buf = image::RgbaImage::from_raw(w as u32, h as u32, bytes)
        .context("screenshot size does not match its pixels")?;
    buf.save(&p)
        .with_context(|| format!("writing {}", p.display()))?;
    Ok(p)
}

impl eframe::App for ViewerApp {
    fn ui(&mut self, ui: &mut egui::Ui, _frame: &mut eframe::Frame) {
        let changed = self.poll();
        self.show(ui);
        let running =
            self.worker.is_some() && self.state.finished.is_none() && self.state.error.is_none();
        if running || changed {
            ui.ctx().request_repaint();
        }
        if !running && self.state.error.is_none() {
            self.step_frame_bench(ui.ctx());
        }
    }
}

impl ViewerApp {
    /// One frame of the [`FrameBench`] measurement (no-op when none is active).
    fn step_frame_bench(&mut self, ctx: &egui::Context) {
        let live_ms = self.median_frame_ms();
        let Some(b) = &mut self.frame_bench else {
            return;
        };
        if b.done {
            return;
        }
        if b.live_ms.is_none() {
            b.live_ms = Some(live_ms.unwrap_or(f64::NAN));
        }
        let now = Instant::now();
        if let Some(t) = b.last.replace(now) {
            b.times_ms.push((now - t).as_secs_f64() * 1e3);
        }
        if b.times_ms.len() >= b.frames {
            b.done = true;
            let mut v = b.times_ms.clone();
            v.sort_by(f64::total_cmp);
            let q = |f: f64| v[((v.len() - 1) as f64 * f).round() as usize];
            let drawn = self.point_budget.map_or(self.state.point_count(), |b| {
                self.state.point_count().min(b as usize)
            });
            let size = ctx.content_rect().size() * ctx.pixels_per_point();
            println!(
                "ui frame: median {:.1} ms, p95 {:.1} ms over {} frames (orbiting); {} points, {drawn} drawn; window {}x{}; live run: median {:.1} ms",
                q(0.5),
                q(0.95),
                v.len(),
                self.state.point_count(),
                size.x.round(),
                size.y.round(),
                b.live_ms.unwrap_or(f64::NAN),
            );
            println!("ready");
            return;
        }
        self.camera.orbit(4.0, 0.0);
        ctx.request_repaint();
    }
}

/// Shows texture `t` scaled to `width` points, keeping its aspect ratio.
fn image_at_width(ui: &mut egui::Ui, t: &TextureHandle, width: f32) {
    let [w, h] = t.size();
    ui.image((t.id(), Vec2::new(width, width * h as f32 / w.max(1) as f32)));
}
