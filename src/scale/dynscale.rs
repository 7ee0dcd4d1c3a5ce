//! Dynamic scale estimation and recursive section scaling (thesis Algorithm 1, eq. 3.31-3.35).
//!
//! The trajectory is resampled at `fps` (linear interpolation of positions). Every `t_upd`
//! seconds (once `t_DFT` seconds are available) the last `t_DFT` seconds of the vertical signal
//! (projection of the camera position on the up axis) are analysed ([`StepAnalysis`]). While
//! walking, the unscaled horizontal speed `V_SLAM` is measured over whole strides (two steps,
//! `2 / f` seconds, as many whole strides as fit in the window) as the horizontal arc length of the positions sampled every <= 0.1 s (the
//! vertical bob is projected out; the lateral sway adds well under 1 %); a window whose stride
//! speeds differ by more than `max_speed_ratio` (a start, stop or pace change) does not update
//! the filter. The walking speed is `V_walk = alpha f^beta H`, and the particle
//! filter updates the scale. Each section (the `t_upd` seconds ending at an update; the first
//! one is the first `t_DFT` seconds) gets the filter's estimate `s_k` at its end; sections
//! before the first estimate get the first estimate (offline; a live system would wait), and
//! standing sections keep the last estimate.
//!
//! Recursive scaling (3.31-3.33): with `o_k` the raw position at the start of section `k`,
//! `o'_0 = o_0`, `o'_{k+1} = o'_k + s_k (o_{k+1} - o_k)`, and for a pose at time `t` in section
//! `k`: `p' = o'_k + s_k (p - o_k)`, velocity `v' = s_k v`, orientation unchanged. A landmark
//! anchored (first seen) at time `t_a` is scaled with its anchor section (3.35):
//! `x' = o'_a + s_a (x - o_a)`.
//!
//! The up axis (3.4.2) is configurable: a fixed direction in the trajectory's world frame
//! (default `-y`: the first camera's up for a monocular SLAM whose world is its first camera,
//! looking roughly horizontally) or `Auto`, the normal of the best-fit plane of the positions
//! (a walk on level ground; not for stairs).

use glam::DVec3;
use serde::{Deserialize, Serialize};

use super::particle::{ParticleConfig, ScaleFilter};
use super::spectrum::{HighPass, SpectrumConfig, StepAnalysis};
use super::walking::WalkingModel;
use super::{check_param, ScaleError};
use crate::geometry::Se3;
use crate::trajectory::TimedPose;

/// The gravity-up direction in the trajectory's world frame.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum UpAxis {
    /// A fixed direction (normalised before use).
    Fixed([f64; 3]),
    /// The normal of the best-fit plane of the positions (least-variance direction).
    Auto,
}

impl UpAxis {
    /// Parses `x`, `-y`, `+z`, `auto` or `a,b,c`.
    pub fn parse(s: &str) -> Result<UpAxis, ScaleError> {
        let t = s.trim().to_ascii_lowercase();
        let bad = || ScaleError::InvalidParameter {
            name: "up",
            why: format!("'{s}': expected x, y, z (optionally signed), auto, or a,b,c"),
        };
        let axis = |c: &str| match c {
            "x" => Some(DVec3::X),
            "y" => Some(DVec3::Y),
            "z" => Some(DVec3::Z),
            _ => None,
        };
        if t == "auto" {
            return Ok(UpAxis::Auto);
        }
        if let Some(rest) = t.strip_prefix('-') {
            if let Some(v) = axis(rest) {
                return Ok(UpAxis::Fixed((-v).to_array()));
            }
        }
        if let Some(v) = axis(t.strip_prefix('+').unwrap_or(&t)) {
            return Ok(UpAxis::Fixed(v.to_array()));
        }
        let parts: Vec<f64> = t
            .split(',')
            .map(|p| p.trim().parse::<f64>())
            .collect::<Result<_, _>>()
            .map_err(|_| bad())?;
        if parts.len() != 3 || parts.iter().any(|v| !v.is_finite()) {
            return Err(bad());
        }
        let v = DVec3::new(parts[0], parts[1], parts[2]);
        if v.length() < 1e-9 {
            return Err(bad());
        }
        Ok(UpAxis::Fixed(v.to_array()))
    }

    /// The unit up vector for `positions` (world frame).
    pub fn resolve(&self, positions: &[DVec3]) -> Result<DVec3, ScaleError> {
        match *self {
            UpAxis::Fixed(v) => {
                let v = DVec3::from_array(v);
                if !(v.length() > 1e-9) || !v.is_finite() {
                    return Err(ScaleError::UpAxis(format!(
                        "fixed axis {v:?} has no direction"
                    )));
                }
                Ok(v.normalize())
            }
            UpAxis::Auto => {
                let n = positions.len();
                if n < 3 {
                    return Err(ScaleError::UpAxis("fewer than 3 positions".into()));
                }
                let m = positions.iter().copied().sum::<DVec3>() / n as f64;
                let mut c = nalgebra::Matrix3::<f64>::zeros();
                for p in positions {
                    let d = nalgebra::Vector3::new(p.x - m.x, p.y - m.y, p.z - m.z);
                    c += d * d.transpose();
                }
                let e = c.symmetric_eigen();
                let mut idx = [0usize, 1, 2];
                idx.sort_by(|&a, &b| e.eigenvalues[a].total_cmp(&e.eigenvalues[b]));
                let (l0, l1) = (e.eigenvalues[idx[0]], e.eigenvalues[idx[1]]);
                if !(l1 > 0.0) || l0 > 0.25 * l1 {
                    return Err(ScaleError::UpAxis(format!(
                        "positions are not spread over a plane (eigenvalues {l0:.3e}, {l1:.3e}); give the axis"
                    )));
                }
                let v = e.eigenvectors.column(idx[0]);
                Ok(DVec3::new(v[0], v[1], v[2]).normalize())
            }
        }
    }
}

/// Settings of the dynamic scale estimation.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct DynScaleConfig {
    /// Resampling rate of the trajectory, frames per second.
    pub fps: f64,
    /// Analysis window `t_DFT`, seconds.
    pub window: f64,
    /// Update period `t_upd`, seconds (the section length).
    pub update: f64,
    /// Spectral analysis settings.
    pub spectrum: SpectrumConfig,
    /// Walking model of the wearer.
    pub model: WalkingModel,
    /// Particle filter settings.
    pub filter: ParticleConfig,
    /// Up axis in the trajectory's world frame.
    pub up: UpAxis,
    /// Largest ratio between the fastest and slowest stride speed in a window for it to count
    /// as steady walking (pace changes, starts and stops fail it and do not update the filter).
    pub max_speed_ratio: f64,
    /// Seed of the particle filter.
    pub seed: u64,
    /// Longest window for the step frequency alone, seconds (`<= window`: off). The
    /// frequency of a walking window is re-read from the longest window ending at the same
    /// time, from this length down in steps of `window / 2`, over which the pace was
    /// stationary: the `window`-long window at the start of the longer one and the longer
    /// one itself must both agree with the current frequency within three standard
    /// deviations of the difference of two short-window estimates
    /// ([`StepAnalysis::frequency_std`]), and at most `stationary_hz`. The periodogram
    /// peak's error falls as `T^-1.5`, so a longer window steadies the frequency of a noisy
    /// estimate; the test keeps pace changes from blurring it. Walking detection, power and
    /// amplitude stay those of `window`.
    #[serde(default = "default_frequency_window")]
    pub frequency_window: f64,
    /// Largest frequency difference, Hz, for the pace to count as stationary over
    /// `frequency_window` (a cap on the noise-based tolerance).
    #[serde(default = "default_stationary_hz")]
    pub stationary_hz: f64,
}

fn default_frequency_window() -> f64 {
    8.0
}

fn default_stationary_hz() -> f64 {
    0.15
}

impl Default for DynScaleConfig {
    /// [`DynScaleConfig::new`] for a walker of 1.70 m at 30 fps (set `model.height` to the
    /// wearer's height).
    fn default() -> Self {
        DynScaleConfig::new(1.7, 30.0)
    }
}

impl DynScaleConfig {
    /// Defaults for a walker of `height` metres (Grieve's model) at `fps`: `t_DFT = 4 s`,
    /// `t_upd = 1 s`, up `-y`.
    pub fn new(height: f64, fps: f64) -> DynScaleConfig {
        DynScaleConfig {
            fps,
            window: 4.0,
            update: 1.0,
            spectrum: SpectrumConfig::default(),
            model: WalkingModel::grieve(height),
            filter: ParticleConfig::default(),
            up: UpAxis::Fixed([0.0, -1.0, 0.0]),
            max_speed_ratio: 1.25,
            seed: 0x5ca1e,
            frequency_window: default_frequency_window(),
            stationary_hz: default_stationary_hz(),
        }
    }
    /// Checks every setting.
    pub fn validate(&self) -> Result<(), ScaleError> {
        check_param(
            "fps",
            self.fps.is_finite() && self.fps > 2.0 * self.spectrum.band.1,
            || format!("{} must exceed twice the band's top frequency", self.fps),
        )?;
        check_param(
            "window",
            self.window.is_finite() && self.window >= 1.0,
            || format!("{} s must be >= 1 s", self.window),
        )?;
        check_param(
            "update",
            self.update.is_finite() && self.update > 0.0 && self.update <= self.window,
            || format!("{} s must be in (0, window]", self.update),
        )?;
        check_param(
            "frequency_window",
            self.frequency_window.is_finite() && self.frequency_window >= 0.0,
            || format!("{} s must be finite and >= 0", self.frequency_window),
        )?;
        check_param(
            "stationary_hz",
            self.stationary_hz.is_finite() && self.stationary_hz >= 0.0,
            || format!("{} Hz must be finite and >= 0", self.stationary_hz),
        )?;
        check_param("max_speed_ratio", self.max_speed_ratio >= 1.0, || {
            format!("{} must be >= 1", self.max_speed_ratio)
        })?;
        self.spectrum.validate()?;
        self.model.validate()?;
        self.filter.validate()
    }
}

/// One section of the trajectory with its analysis and scale.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Section {
    /// Start of the section, seconds (trajectory time stamps).
    pub t_start: f64,
    /// End of the section (the update time), seconds.
    pub t_end: f64,
    /// Start of the analysis window that ends at `t_end`, seconds.
    pub window_start: f64,
    /// Spectral analysis of that window (its `frequency` read from the longer window of
    /// [`DynScaleConfig::frequency_window`] when the pace was stationary over it).
    pub analysis: StepAnalysis,
    /// Length of the window the step frequency was read from, seconds.
    #[serde(default)]
    pub frequency_span: f64,
    /// Whether the window was detected as walking.
    pub walking: bool,
    /// Whether the per-stride speeds in the window agree within `max_speed_ratio` (only steady
    /// walking windows update the filter).
    pub steady: bool,
    /// Unscaled horizontal speed, SLAM units/s (0 when not walking).
    pub v_slam: f64,
    /// Walking speed `alpha f^beta H`, m/s (0 when not walking).
    pub v_walk: f64,
    /// Whether the filter accepted the measurement (false when not walking).
    pub consistent: bool,
    /// Scale of the section, metres per SLAM unit.
    pub scale: f64,
    /// Spread of `log10 s` in the filter after the update, decades (NaN before any update).
    pub log10_std: f64,
    /// Raw position at the section start (SLAM units, world frame).
    pub origin_raw: [f64; 3],
    /// Scaled position at the section start (metres, world frame).
    pub origin_scaled: [f64; 3],
}

impl Section {
    /// Metric speed of the section, `scale * v_slam`, m/s.
    pub fn speed(&self) -> f64 {
        self.scale * self.v_slam
    }
}

/// Result of [`DynScale::run`].
#[derive(Clone, Debug)]
pub struct DynScaleResult {
    /// Sections in time order; they tile `[first time stamp, last time stamp]`.
    pub sections: Vec<Section>,
    /// Up axis used (unit vector, world frame).
    pub up: [f64; 3],
    /// The input trajectory, recursively scaled (`world_from_camera`, metres).
    pub scaled: Vec<TimedPose>,
}

impl DynScaleResult {
    /// The section containing time `t` (the first / last for times outside).
    pub fn section_at(&self, t: f64) -> &Section {
        let k = self.sections.partition_point(|s| s.t_start <= t);
        &self.sections[k.saturating_sub(1).min(self.sections.len() - 1)]
    }
    /// Scale (metres per SLAM unit) in effect at time `t`.
    pub fn scale_at(&self, t: f64) -> f64 {
        self.section_at(t).scale
    }
    /// Scales a raw position observed at time `t` (eq. 3.31-3.32).
    pub fn scale_position(&self, t: f64, p: DVec3) -> DVec3 {
        let s = self.section_at(t);
        DVec3::from_array(s.origin_scaled) + s.scale * (p - DVec3::from_array(s.origin_raw))
    }
    /// Scales a raw velocity (SLAM units/s) at time `t` to m/s (eq. 3.33).
    pub fn scale_velocity(&self, t: f64, v: DVec3) -> DVec3 {
        self.scale_at(t) * v
    }
    /// Scales a landmark anchored (first observed) at time `anchor_time` (eq. 3.35).
    pub fn scale_landmark(&self, anchor_time: f64, x: DVec3) -> DVec3 {
        self.scale_position(anchor_time, x)
    }
}

/// Sections of Algorithm 1, the filter's estimate after each, and the up axis.
type Analysis = (Vec<Section>, Vec<Option<f64>>, DVec3);

/// The resampled signals one window of Algorithm 1 reads: the positions on the time grid
/// `t0 + k / fps` and the high-passed vertical signal, both from absolute sample `first` on
/// (0 offline; a live estimator holds the last few seconds only).
#[derive(Clone, Copy, Debug)]
pub(crate) struct GridView<'a> {
    /// Time of grid sample 0, seconds.
    pub t0: f64,
    /// Grid rate, samples per second.
    pub fps: f64,
    /// Absolute index of `grid[0]` and `hp[0]`.
    pub first: usize,
    /// Positions, SLAM units, world frame.
    pub grid: &'a [DVec3],
    /// High-passed projection of the positions on `up`.
    pub hp: &'a [f64],
    /// Unit up vector, world frame.
    pub up: DVec3,
}

impl GridView<'_> {
    /// One past the absolute index of the last sample.
    pub fn len(&self) -> usize {
        self.first + self.grid.len().min(self.hp.len())
    }

    /// The high-passed samples `a..=b` (absolute indices, clamped to those held).
    pub fn hp_range(&self, a: usize, b: usize) -> &[f64] {
        let held = self.grid.len().min(self.hp.len());
        let hi = (b + 1).saturating_sub(self.first).min(held);
        let lo = a.saturating_sub(self.first).min(hi);
        &self.hp[lo..hi]
    }

    /// The horizontal part of the position at time `t` (linear between grid samples, clamped
    /// to the samples held).
    pub fn horizontal(&self, t: f64) -> DVec3 {
        let n = self.len();
        let held = n - self.first;
        if held == 0 {
            return DVec3::ZERO;
        }
        let x = ((t - self.t0) * self.fps).clamp(self.first as f64, (n - 1) as f64);
        let i = (x.floor() as usize)
            .min(n.saturating_sub(2))
            .max(self.first);
        let a = self.grid[i - self.first];
        let b = self.grid[(i + 1 - self.first).min(held - 1)];
        let p = a.lerp(b, x - i as f64);
        p - p.dot(self.up) * self.up
    }

    /// Horizontal arc length over the `duration` seconds ending at `t_hi`, as `pieces` chords
    /// (summed from the end backwards).
    pub fn path(&self, t_hi: f64, duration: f64, pieces: usize) -> f64 {
        (0..pieces)
            .map(|q| {
                let ta = t_hi - duration * (q + 1) as f64 / pieces as f64;
                let tb = t_hi - duration * q as f64 / pieces as f64;
                (self.horizontal(tb) - self.horizontal(ta)).length()
            })
            .sum()
    }
}

/// What Algorithm 1 carries from one window to the next: the particle filter and the time of
/// its last update.
#[derive(Clone, Debug)]
pub(crate) struct WindowState {
    /// The scale filter.
    pub filter: ScaleFilter,
    /// Time of the last filter update, seconds.
    pub last_update: Option<f64>,
}

impl WindowState {
    /// A fresh filter seeded by `cfg.seed`.
    pub fn new(cfg: &DynScaleConfig) -> Result<WindowState, ScaleError> {
        Ok(WindowState {
            filter: ScaleFilter::new(cfg.filter.clone(), cfg.seed)?,
            last_update: None,
        })
    }
}

/// The dynamic scale estimator (Algorithm 1).
#[derive(Clone, Debug)]
pub struct DynScale {
    cfg: DynScaleConfig,
}

/// Linear interpolation of the position at time `t` (clamped to the trajectory's span).
pub fn interpolate_position(traj: &[TimedPose], t: f64) -> DVec3 {
    let k = traj.partition_point(|p| p.timestamp <= t);
    if k == 0 {
        return traj[0].world_from_camera.translation;
    }
    if k >= traj.len() {
        return traj[traj.len() - 1].world_from_camera.translation;
    }
    let (a, b) = (&traj[k - 1], &traj[k]);
    let u = ((t - a.timestamp) / (b.timestamp - a.timestamp)).clamp(0.0, 1.0);
    a.world_from_camera
        .translation
        .lerp(b.world_from_camera.translation, u)
}

/// Checks that a trajectory is non-empty, finite and strictly increasing in time.
pub fn check_trajectory(traj: &[TimedPose]) -> Result<(), ScaleError> {
    if traj.len() < 2 {
        return Err(ScaleError::TooShort {
            have: traj.len(),
            seconds: 0.0,
            need: "2 poses at least".into(),
        });
    }
    for (i, p) in traj.iter().enumerate() {
        if !p.timestamp.is_finite() || !p.world_from_camera.is_finite() {
            return Err(ScaleError::NonFinite(format!("pose {i}")));
        }
        if i > 0 && !(p.timestamp > traj[i - 1].timestamp) {
            return Err(ScaleError::BadTimestamps(format!(
                "pose {i} at {} s does not follow {} s",
                p.timestamp,
                traj[i - 1].timestamp
            )));
        }
    }
    Ok(())
}

impl DynScale {
    /// An estimator with `cfg` (validated).
    pub fn new(cfg: DynScaleConfig) -> Result<DynScale, ScaleError> {
        cfg.validate()?;
        Ok(DynScale { cfg })
    }
    /// The settings.
    pub fn config(&self) -> &DynScaleConfig {
        &self.cfg
    }

    /// Runs Algorithm 1 over `traj` (`world_from_camera`, time stamps in seconds, strictly
    /// increasing) and returns the sections and the scaled trajectory.
    pub fn run(&self, traj: &[TimedPose]) -> Result<DynScaleResult, ScaleError> {
        let (sections, scales, up) = self.analyse(traj)?;
        self.finish(traj, sections, scales, up)
    }

    /// The sections of Algorithm 1 (analysis, walking, filter update) with the filter's
    /// estimate after each (`None` before the first update), and the up axis; the sections'
    /// `scale` and origins are not set yet.
    fn analyse(&self, traj: &[TimedPose]) -> Result<Analysis, ScaleError> {
        check_trajectory(traj)?;
        let c = &self.cfg;
        let t0 = traj[0].timestamp;
        let span = traj[traj.len() - 1].timestamp - t0;
        if span < c.window {
            return Err(ScaleError::TooShort {
                have: traj.len(),
                seconds: span,
                need: format!("{} s (one analysis window)", c.window),
            });
        }
        let n = (span * c.fps).floor() as usize + 1;
        let grid: Vec<DVec3> = (0..n)
            .map(|k| interpolate_position(traj, t0 + k as f64 / c.fps))
            .collect();
        let up = c.up.resolve(&grid)?;
        let vertical: Vec<f64> = grid.iter().map(|p| p.dot(up)).collect();
        let hp = HighPass::filter_signal(c.spectrum.highpass_hz, c.fps, &vertical)?;
        let view = GridView {
            t0,
            fps: c.fps,
            first: 0,
            grid: &grid,
            hp: &hp,
            up,
        };
        let mut state = WindowState::new(c)?;
        let mut sections: Vec<Section> = Vec::new();
        let mut scales: Vec<Option<f64>> = Vec::new();
        let mut t_prev = t0;
        let mut j = 0usize;
        loop {
            let t_end = t0 + c.window + j as f64 * c.update;
            if t_end > t0 + span + 1e-9 {
                break;
            }
            sections.push(self.window_step(&mut state, &view, t_prev, t_end)?);
            scales.push(state.filter.estimate());
            t_prev = t_end;
            j += 1;
        }
        Ok((sections, scales, up))
    }

    /// One section of Algorithm 1: the window of `t_DFT` seconds ending at `t_end` (seconds)
    /// is analysed on `view`, and a steady walking window updates the filter in `state`.
    /// The section spans `[t_start, t_end]`; its `scale` and origins are not set.
    pub(crate) fn window_step(
        &self,
        state: &mut WindowState,
        view: &GridView<'_>,
        t_start: f64,
        t_end: f64,
    ) -> Result<Section, ScaleError> {
        let c = &self.cfg;
        let t0 = view.t0;
        let n = view.len();
        let nw = (c.window * c.fps).round() as usize;
        let e = (((t_end - t0) * c.fps).round() as usize).min(n.saturating_sub(1));
        let s = (e + 1).saturating_sub(nw).max(view.first);
        let filter = &mut state.filter;
        // The step frequency the walking model expects at the window's mean horizontal
        // speed and the current scale (none before the first estimate).
        let hint = filter.estimate().map(|scale| {
            let duration = (t_end - (t0 + s as f64 / c.fps)).max(1e-9);
            let pieces = (duration / 0.1).ceil().max(1.0) as usize;
            c.model
                .frequency(scale * view.path(t_end, duration, pieces) / duration)
        });
        let mut analysis =
            StepAnalysis::analyze_with_hint(view.hp_range(s, e), c.fps, &c.spectrum, hint)?;
        let mut walking = analysis.is_walking(&c.spectrum, filter.estimate());
        let mut frequency_span = (e + 1 - s) as f64 / c.fps;
        if walking {
            if let Some((f, span)) = self.stationary_frequency(
                view,
                e,
                analysis.frequency,
                analysis.frequency_std,
                hint,
            )? {
                analysis.frequency = f;
                frequency_span = span;
            }
        }
        let (mut v_slam, mut v_walk, mut consistent, mut log10_std) = (0.0, 0.0, false, f64::NAN);
        let mut steady = false;
        if walking {
            let f = analysis.frequency;
            let stride = 2.0 / f;
            let k = ((c.window / stride).floor() as usize).max(1);
            let sub = ((stride / 0.1).ceil() as usize).max(1);
            let mut stride_speeds = Vec::with_capacity(k);
            for m in 0..k {
                let t_hi = t_end - m as f64 * stride;
                stride_speeds.push(view.path(t_hi, stride, sub) / stride);
            }
            v_slam = stride_speeds.iter().sum::<f64>() / k as f64;
            let vmin = stride_speeds.iter().cloned().fold(f64::INFINITY, f64::min);
            let vmax = stride_speeds.iter().cloned().fold(0.0, f64::max);
            steady = vmin > 0.0 && vmax <= c.max_speed_ratio * vmin;
            v_walk = c.model.speed(f);
            if v_slam > 0.0 && v_walk > 0.0 && steady {
                let dt = state.last_update.map_or(0.0, |t| t_end - t);
                let u = filter.update(v_slam, v_walk, dt)?;
                state.last_update = Some(t_end);
                consistent = u.consistent;
                log10_std = u.log10_std;
            } else if !(v_slam > 0.0) {
                walking = false;
                v_slam = 0.0;
                v_walk = 0.0;
            }
        }
        let zero = [0.0; 3];
        Ok(Section {
            t_start,
            t_end,
            window_start: t0 + s as f64 / c.fps,
            analysis,
            frequency_span,
            walking,
            steady,
            v_slam,
            v_walk,
            consistent,
            scale: f64::NAN,
            log10_std,
            origin_raw: zero,
            origin_scaled: zero,
        })
    }

    /// The step frequency from the longest window ending at sample `e` of the high-passed
    /// vertical signal of `view` over which the pace was stationary
    /// ([`DynScaleConfig::frequency_window`]): lengths from `frequency_window` down in steps
    /// of `window / 2`, longer than `window`; a length is taken when both the `window`-long
    /// analysis at its start and the whole long one are within three standard deviations
    /// ([`StepAnalysis::frequency_std`] of both short windows; at most `stationary_hz`) of
    /// the current window's frequency `f` (standard deviation `f_std`). Returns the
    /// frequency (Hz) and the length used (seconds), or `None` when no longer window passes.
    fn stationary_frequency(
        &self,
        view: &GridView<'_>,
        e: usize,
        f: f64,
        f_std: f64,
        hint: Option<f64>,
    ) -> Result<Option<(f64, f64)>, ScaleError> {
        let c = &self.cfg;
        let nw = (c.window * c.fps).round() as usize;
        let step = ((0.5 * c.window * c.fps).round() as usize).max(1);
        let mut nl = (c.frequency_window * c.fps).round() as usize;
        let analyse = |a: usize, b: usize| {
            StepAnalysis::analyze_with_hint(view.hp_range(a, b), c.fps, &c.spectrum, hint)
        };
        while nl > nw {
            // Only windows that lie inside the samples held (all of them offline).
            if e + 1 >= nl && e + 1 - nl >= view.first {
                let sl = e + 1 - nl;
                let first = analyse(sl, sl + nw - 1)?;
                // Two estimates of one stationary pace differ by noise alone: within three
                // standard deviations of their difference (at most `stationary_hz`).
                let tolerance = (3.0 * first.frequency_std.hypot(f_std)).min(c.stationary_hz);
                if (first.frequency - f).abs() <= tolerance {
                    let f_long = analyse(sl, e)?.frequency;
                    if (f_long - f).abs() <= tolerance {
                        return Ok(Some((f_long, nl as f64 / c.fps)));
                    }
                }
            }
            nl = nl.saturating_sub(step);
        }
        Ok(None)
    }

    /// Sets the sections' scales (backfilled before the first update) and origins, adds the
    /// tail after the last update, and scales the trajectory.
    pub(crate) fn finish(
        &self,
        traj: &[TimedPose],
        mut sections: Vec<Section>,
        mut scales: Vec<Option<f64>>,
        up: DVec3,
    ) -> Result<DynScaleResult, ScaleError> {
        let t0 = traj[0].timestamp;
        let span = traj[traj.len() - 1].timestamp - t0;
        let t_prev = sections.last().map_or(t0, |s| s.t_end);
        let windows = sections.len();
        let first = scales
            .iter()
            .flatten()
            .next()
            .copied()
            .ok_or(ScaleError::NoWalking { windows })?;
        // The tail after the last update keeps the last scale.
        let t_last = t0 + span;
        if t_last > t_prev + 1e-9 {
            if let Some(last) = sections.last().copied() {
                sections.push(Section {
                    t_start: t_prev,
                    t_end: t_last,
                    walking: false,
                    steady: false,
                    consistent: false,
                    v_slam: 0.0,
                    v_walk: 0.0,
                    ..last
                });
                scales.push(*scales.last().unwrap_or(&None));
            }
        }
        let mut current = first;
        let mut o_scaled = interpolate_position(traj, t0);
        let mut o_raw = o_scaled;
        let mut prev_scale = first;
        for (k, sec) in sections.iter_mut().enumerate() {
            if let Some(s) = scales[k] {
                current = s;
            }
            let raw = interpolate_position(traj, sec.t_start);
            if k > 0 {
                o_scaled += prev_scale * (raw - o_raw);
            }
            o_raw = raw;
            sec.scale = current;
            sec.origin_raw = o_raw.to_array();
            sec.origin_scaled = o_scaled.to_array();
            prev_scale = current;
        }
        let mut result = DynScaleResult {
            sections,
            up: up.to_array(),
            scaled: Vec::new(),
        };
        result.scaled = traj
            .iter()
            .map(|p| TimedPose {
                timestamp: p.timestamp,
                world_from_camera: Se3::new(
                    p.world_from_camera.rotation,
                    result.scale_position(p.timestamp, p.world_from_camera.translation),
                ),
            })
            .collect();
        Ok(result)
    }
}
