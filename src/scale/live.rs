//! Algorithm 1 on a live stream (the scaling thread beside a monocular SLAM).
//!
//! [`LiveDynScale`] takes one pose at a time and does a bounded amount of work per pose and
//! per update, whatever the length of the trajectory so far: the poses are resampled onto the
//! time grid `t0 + k / fps` as they arrive, the vertical signal is high-passed sample by
//! sample (the same causal filter as offline), and only the last
//! `max(t_DFT, frequency_window)` seconds (plus a margin) of the grid are held. Every `t_upd`
//! seconds the window ending at the section's end is analysed exactly as by
//! [`DynScale::run`] (the same code), so with a fixed up axis the sections reported live are
//! bit for bit those of an offline run.
//!
//! Up axis found online ([`UpAxis::Auto`]): every `t_upd` seconds the last `t_DFT` seconds of
//! the positions are detrended, the direction of travel over the window is projected out
//! (travel is horizontal, and forward surges are not the vertical bob), and the covariance of
//! what remains in the step band (1-3 Hz; the lateral sway at half the step frequency lies
//! mostly below it) is taken from the FFT of the three coordinates. Windows whose dominant
//! oscillation looks like walking ([`StepAnalysis::is_walking`] on its projection) are summed,
//! each normalised to unit trace; after `UP_WINDOWS` of them the dominant direction of the sum
//! is the up axis when it holds at least `UP_EIGEN_RATIO` times the power of the next one. It
//! is then held; its sign is the camera's mean up (`-y` of the camera, in the world frame),
//! which does not matter to the scale. Until then sections are reported as not walking.
//!
//! Section scaling (eq. 3.31-3.35) is given two ways: causally ([`LiveDynScale::scaled_pose`],
//! [`LiveDynScale::anchor_transform`]: the scale known at that moment, origins chained with
//! the scale each section was output with), and as the final output
//! ([`LiveDynScale::finish`]: each section with the scale at its end, the sections before the
//! first estimate with the first one, as offline).

use std::collections::VecDeque;

use glam::DVec3;
use rustfft::{num_complex::Complex, FftPlanner};

use super::dynscale::{
    DynScale, DynScaleConfig, DynScaleResult, GridView, Section, UpAxis, WindowState,
};
use super::spectrum::{HighPass, StepAnalysis};
use super::ScaleError;
use crate::trajectory::TimedPose;

/// Walking windows summed before the up axis is decided.
const UP_WINDOWS: usize = 3;
/// Power of the dominant in-band oscillation direction over the next one needed to fix the up
/// axis.
const UP_EIGEN_RATIO: f64 = 3.0;

/// The affine map of eq. 3.31-3.35 for one section: `p' = origin_scaled + scale (p -
/// origin_raw)`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SectionTransform {
    /// Raw position at the section start, SLAM units, world frame.
    pub origin_raw: DVec3,
    /// Scaled position at the section start, metres, world frame.
    pub origin_scaled: DVec3,
    /// Scale of the section, metres per SLAM unit.
    pub scale: f64,
}

impl SectionTransform {
    /// A raw position (SLAM units) in metres.
    pub fn apply(&self, p: DVec3) -> DVec3 {
        self.origin_scaled + self.scale * (p - self.origin_raw)
    }
}

/// Online search for the up axis from the direction of the vertical oscillation.
#[derive(Clone, Debug)]
struct UpFinder {
    sum: nalgebra::Matrix3<f64>,
    windows: usize,
    camera_up: DVec3,
}

/// Algorithm 1 fed one pose at a time (see the module documentation): every `t_upd` seconds
/// of input (once one `t_DFT` window is in) it closes a section and reports it with its
/// scale. Work per pose and per update is independent of the trajectory's length.
#[derive(Clone, Debug)]
pub struct LiveDynScale {
    estimator: DynScale,
    state: WindowState,
    up: Option<DVec3>,
    finder: Option<UpFinder>,
    t0: Option<f64>,
    last: Option<TimedPose>,
    /// Absolute index of `grid[0]`.
    first: usize,
    grid: VecDeque<DVec3>,
    hp: VecDeque<f64>,
    highpass: Option<(HighPass, f64)>,
    keep: usize,
    /// Closed sections (scale: the filter's estimate at their end, NaN before the first).
    sections: Vec<Section>,
    /// Raw position at each section start passed so far (index = section).
    origins_raw: Vec<DVec3>,
    /// Causal scaled position at each section start, once a scale exists.
    origins_scaled: Vec<Option<DVec3>>,
    /// Scale each passed section was output with (causal chain).
    chain_scales: Vec<f64>,
}

impl LiveDynScale {
    /// A live estimator with `cfg` (validated); with [`UpAxis::Auto`] the up axis is found
    /// online and then held.
    pub fn new(cfg: DynScaleConfig) -> Result<LiveDynScale, ScaleError> {
        let keep = ((cfg.window.max(cfg.frequency_window) + 2.0 * cfg.update + 1.0) * cfg.fps)
            .ceil() as usize;
        let estimator = DynScale::new(cfg)?;
        let c = estimator.config();
        let (up, finder) = match c.up {
            UpAxis::Fixed(_) => (Some(c.up.resolve(&[])?), None),
            UpAxis::Auto => (
                None,
                Some(UpFinder {
                    sum: nalgebra::Matrix3::zeros(),
                    windows: 0,
                    camera_up: DVec3::ZERO,
                }),
            ),
        };
        Ok(LiveDynScale {
            state: WindowState::new(c)?,
            estimator,
            up,
            finder,
            t0: None,
            last: None,
            first: 0,
            grid: VecDeque::with_capacity(keep + 2),
            hp: VecDeque::with_capacity(keep + 2),
            highpass: None,
            keep,
            sections: Vec::new(),
            origins_raw: Vec::new(),
            origins_scaled: Vec::new(),
            chain_scales: Vec::new(),
        })
    }

    /// The settings.
    pub fn config(&self) -> &DynScaleConfig {
        self.estimator.config()
    }

    /// The up axis (unit vector, world frame), once fixed or found.
    pub fn up(&self) -> Option<DVec3> {
        self.up
    }

    /// Grid samples held now (bounded by the window lengths, not by the trajectory).
    pub fn samples_held(&self) -> usize {
        self.grid.len()
    }

    /// The sections closed so far, in time order.
    pub fn sections(&self) -> &[Section] {
        &self.sections
    }

    /// End time of section `j`, seconds.
    fn section_end(&self, t0: f64, j: usize) -> f64 {
        let c = self.estimator.config();
        t0 + c.window + j as f64 * c.update
    }

    /// Adds the next pose (`world_from_camera`, SLAM units; time stamps strictly increasing).
    /// Returns the sections closed by it (usually none, one per `t_upd` seconds), with their
    /// walking flag and scale (metres per SLAM unit; NaN before the first walking window).
    pub fn push(&mut self, pose: TimedPose) -> Result<Vec<Section>, ScaleError> {
        if !pose.timestamp.is_finite() || !pose.world_from_camera.is_finite() {
            return Err(ScaleError::NonFinite(format!(
                "pose at {} s",
                pose.timestamp
            )));
        }
        if let Some(last) = &self.last {
            if !(pose.timestamp > last.timestamp) {
                return Err(ScaleError::BadTimestamps(format!(
                    "{} s after {} s",
                    pose.timestamp, last.timestamp
                )));
            }
        }
        let p = pose.world_from_camera.translation;
        let fps = self.estimator.config().fps;
        let t0 = *self.t0.get_or_insert(pose.timestamp);
        if let Some(f) = &mut self.finder {
            f.camera_up += pose.world_from_camera.transform_vector(DVec3::NEG_Y);
        }
        match self.last {
            None => {
                self.origins_raw.push(p);
                self.origins_scaled.push(None);
            }
            Some(last) => {
                let a = last.world_from_camera.translation;
                let lerp = |t: f64| {
                    let u =
                        ((t - last.timestamp) / (pose.timestamp - last.timestamp)).clamp(0.0, 1.0);
                    a.lerp(p, u)
                };
                // Grid samples in [last, pose) (interpolate_position's bracketing).
                loop {
                    let k = self.first + self.grid.len();
                    let t = t0 + k as f64 / fps;
                    if !(t < pose.timestamp) {
                        break;
                    }
                    self.add_sample(lerp(t))?;
                }
                // Section starts passed.
                loop {
                    let j = self.origins_raw.len() - 1;
                    let tb = self.section_end(t0, j);
                    if !(tb < pose.timestamp) {
                        break;
                    }
                    self.pass_boundary(lerp(tb));
                }
            }
        }
        self.last = Some(pose);
        self.close_due(false)
    }

    /// Closes the sections that end at or before the last pose even where the grid sample
    /// after their end is not in yet (the end of a stream).
    pub fn flush(&mut self) -> Result<Vec<Section>, ScaleError> {
        if let (Some(last), Some(t0)) = (self.last, self.t0) {
            let fps = self.estimator.config().fps;
            let k = self.first + self.grid.len();
            if t0 + k as f64 / fps <= last.timestamp {
                self.add_sample(last.world_from_camera.translation)?;
            }
        }
        self.close_due(true)
    }

    /// One new grid sample (absolute index `first + grid.len()`).
    fn add_sample(&mut self, p: DVec3) -> Result<(), ScaleError> {
        self.grid.push_back(p);
        if let Some(up) = self.up {
            let c = self.estimator.config();
            let v = p.dot(up);
            let (hpf, x0) = self
                .highpass
                .get_or_insert(HighPass::new(c.spectrum.highpass_hz, c.fps).map(|h| (h, v))?);
            let y = hpf.step(v - *x0);
            self.hp.push_back(y);
        }
        while self.grid.len() > self.keep {
            self.grid.pop_front();
            if self.up.is_some() {
                self.hp.pop_front();
            }
            self.first += 1;
        }
        Ok(())
    }

    /// The start of the next section passed at raw position `p`.
    fn pass_boundary(&mut self, p: DVec3) {
        let k = self.origins_raw.len() - 1;
        let scale = self.state.filter.estimate();
        let next = match (self.origins_scaled[k], scale) {
            (Some(o), Some(s)) => {
                self.chain_scales.push(s);
                Some(o + s * (p - self.origins_raw[k]))
            }
            _ => {
                self.chain_scales.push(f64::NAN);
                None
            }
        };
        self.origins_raw.push(p);
        self.origins_scaled.push(next);
    }

    /// Closes the sections whose window is complete (or, with `end`, every one ending by the
    /// last pose).
    fn close_due(&mut self, end: bool) -> Result<Vec<Section>, ScaleError> {
        let (Some(t0), Some(last)) = (self.t0, self.last) else {
            return Ok(Vec::new());
        };
        let c = self.estimator.config().clone();
        let mut closed = Vec::new();
        loop {
            let j = self.sections.len();
            let t_end = self.section_end(t0, j);
            let e = ((t_end - t0) * c.fps).round() as usize;
            let have = self.first + self.grid.len();
            let due = if end {
                t_end <= last.timestamp + 1e-9
            } else {
                have > e + 1
            };
            if !due {
                break;
            }
            let t_start = if j == 0 {
                t0
            } else {
                self.section_end(t0, j - 1)
            };
            if self.up.is_none() {
                self.try_find_up(t_end)?;
            }
            let mut sec = match self.up {
                Some(up) => {
                    let grid = self.grid.make_contiguous();
                    let hp = self.hp.make_contiguous();
                    let view = GridView {
                        t0,
                        fps: c.fps,
                        first: self.first,
                        grid,
                        hp,
                        up,
                    };
                    self.estimator
                        .window_step(&mut self.state, &view, t_start, t_end)?
                }
                None => unobserved_section(t_start, t_end, c.window),
            };
            let scale = self.state.filter.estimate();
            if let (Some(s), true) = (scale, self.origins_scaled.iter().all(Option::is_none)) {
                // The first estimate: the sections before it take it (as offline).
                let o0 = self.origins_raw[0];
                for (k, o) in self.origins_scaled.iter_mut().enumerate() {
                    *o = Some(o0 + s * (self.origins_raw[k] - o0));
                }
                for v in &mut self.chain_scales {
                    *v = s;
                }
            }
            sec.scale = scale.unwrap_or(f64::NAN);
            if let Some(o) = self.origins_raw.get(j) {
                sec.origin_raw = o.to_array();
            }
            if let Some(Some(o)) = self.origins_scaled.get(j) {
                sec.origin_scaled = o.to_array();
            }
            self.sections.push(sec);
            closed.push(sec);
        }
        Ok(closed)
    }

    /// Looks for the up axis in the window ending at `t_end` (seconds).
    fn try_find_up(&mut self, t_end: f64) -> Result<(), ScaleError> {
        let Some(t0) = self.t0 else { return Ok(()) };
        let c = self.estimator.config().clone();
        let nw = (c.window * c.fps).round() as usize;
        let e = ((t_end - t0) * c.fps).round() as usize;
        let have = self.first + self.grid.len();
        if e + 1 > have || e + 1 < nw + self.first {
            return Ok(());
        }
        let grid = self.grid.make_contiguous();
        let window = &grid[e + 1 - nw - self.first..e + 1 - self.first];
        let Some(f) = &mut self.finder else {
            return Ok(());
        };
        if let Some(cov) = band_covariance(window, c.fps, c.spectrum.band, c.spectrum.min_fft_len) {
            let eig = cov.symmetric_eigen();
            let k = eig.eigenvalues.imax();
            let v = eig.eigenvectors.column(k);
            let dir = DVec3::new(v[0], v[1], v[2]);
            let signal: Vec<f64> = window.iter().map(|p| p.dot(dir)).collect();
            let hp = HighPass::filter_signal(c.spectrum.highpass_hz, c.fps, &signal)?;
            let a = StepAnalysis::analyze(&hp, c.fps, &c.spectrum)?;
            if a.is_walking(&c.spectrum, None) {
                let trace = cov.trace();
                if trace > 0.0 {
                    f.sum += cov / trace;
                    f.windows += 1;
                }
            }
        }
        if f.windows >= UP_WINDOWS {
            let eig = f.sum.symmetric_eigen();
            let mut idx = [0usize, 1, 2];
            idx.sort_by(|&a, &b| eig.eigenvalues[b].total_cmp(&eig.eigenvalues[a]));
            let (l0, l1) = (eig.eigenvalues[idx[0]], eig.eigenvalues[idx[1]]);
            if l0 >= UP_EIGEN_RATIO * l1.max(0.0) && l0 > 0.0 {
                let v = eig.eigenvectors.column(idx[0]);
                let mut up = DVec3::new(v[0], v[1], v[2]).normalize();
                if up.dot(f.camera_up) < 0.0 {
                    up = -up;
                }
                if up.is_finite() {
                    self.fix_up(up)?;
                }
            }
        }
        Ok(())
    }

    /// Holds `up` from now on and high-passes the samples held along it.
    fn fix_up(&mut self, up: DVec3) -> Result<(), ScaleError> {
        let c = self.estimator.config();
        let vertical: Vec<f64> = self.grid.iter().map(|p| p.dot(up)).collect();
        let mut hpf = HighPass::new(c.spectrum.highpass_hz, c.fps)?;
        let x0 = vertical.first().copied().unwrap_or(0.0);
        self.hp = vertical.iter().map(|&v| hpf.step(v - x0)).collect();
        self.highpass = Some((hpf, x0));
        self.up = Some(up);
        self.finder = None;
        Ok(())
    }

    /// The scale in effect now (metres per SLAM unit); `None` until the first walking window.
    pub fn scale(&self) -> Option<f64> {
        self.state.filter.estimate()
    }

    /// The causal affine map (eq. 3.31-3.32) of the section containing time `t` (seconds),
    /// as output at the latest pose: that section's causal origin and its scale (the one at
    /// its end once closed, else the scale now). `None` until the first estimate, and for
    /// times after the latest pose.
    pub fn anchor_transform(&self, t: f64) -> Option<SectionTransform> {
        let t0 = self.t0?;
        let last = self.last?;
        if t > last.timestamp {
            return None;
        }
        let c = self.estimator.config();
        let j = if t < t0 + c.window {
            0
        } else {
            (((t - t0 - c.window) / c.update).floor() as usize + 1).min(self.origins_raw.len() - 1)
        };
        let scale = match self.sections.get(j) {
            Some(s) if s.scale.is_finite() => s.scale,
            _ => self.scale()?,
        };
        Some(SectionTransform {
            origin_raw: self.origins_raw[j],
            origin_scaled: self.origins_scaled[j]?,
            scale,
        })
    }

    /// The latest pose scaled to metres with the scale known now (causal; eq. 3.31-3.32);
    /// `None` until the first walking window.
    pub fn scaled_pose(&self) -> Option<TimedPose> {
        let p = self.last?;
        let k = self.origins_raw.len() - 1;
        let o = self.origins_scaled[k]?;
        let s = self.scale()?;
        Some(TimedPose {
            timestamp: p.timestamp,
            world_from_camera: crate::geometry::Se3::new(
                p.world_from_camera.rotation,
                o + s * (p.world_from_camera.translation - self.origins_raw[k]),
            ),
        })
    }

    /// The final output: closes the remaining sections ([`Self::flush`]) and scales `traj`
    /// (the poses pushed, in SLAM units) section by section as [`DynScale::run`] does (each
    /// section with the scale at its end, those before the first estimate with the first).
    pub fn finish(&mut self, traj: &[TimedPose]) -> Result<DynScaleResult, ScaleError> {
        self.flush()?;
        let up = self.up.ok_or(ScaleError::NoWalking {
            windows: self.sections.len(),
        })?;
        let scales: Vec<Option<f64>> = self
            .sections
            .iter()
            .map(|s| s.scale.is_finite().then_some(s.scale))
            .collect();
        self.estimator
            .finish(traj, self.sections.clone(), scales, up)
    }
}

/// A section closed before the up axis is known: nothing measured, not walking.
fn unobserved_section(t_start: f64, t_end: f64, window: f64) -> Section {
    Section {
        t_start,
        t_end,
        window_start: t_end - window,
        analysis: StepAnalysis {
            frequency: 0.0,
            peak_power: 0.0,
            band_power: 0.0,
            total_power: 0.0,
            amplitude: 0.0,
            concentration: 0.0,
            frequency_std: f64::INFINITY,
        },
        frequency_span: 0.0,
        walking: false,
        steady: false,
        v_slam: 0.0,
        v_walk: 0.0,
        consistent: false,
        scale: f64::NAN,
        log10_std: f64::NAN,
        origin_raw: [0.0; 3],
        origin_scaled: [0.0; 3],
    }
}

/// Covariance of the oscillation of `window` (positions at `fps`) in `band` (Hz) across the
/// direction of travel: each coordinate detrended (least-squares line), the travel direction
/// (first to last position) projected out, Hann-windowed FFT, `sum Re(X X^H)` over the band's
/// bins. `None` for fewer than 8 samples or no motion at all.
fn band_covariance(
    window: &[DVec3],
    fps: f64,
    band: (f64, f64),
    min_fft_len: usize,
) -> Option<nalgebra::Matrix3<f64>> {
    let n = window.len();
    if n < 8 {
        return None;
    }
    let travel = window[n - 1] - window[0];
    let along = if travel.length() > 1e-12 {
        travel.normalize()
    } else {
        DVec3::ZERO
    };
    let tm = 0.5 * (n - 1) as f64;
    let stt: f64 = (0..n).map(|i| (i as f64 - tm).powi(2)).sum();
    let mean = window.iter().copied().sum::<DVec3>() / n as f64;
    let slope = window
        .iter()
        .enumerate()
        .map(|(i, p)| (i as f64 - tm) * (*p - mean))
        .sum::<DVec3>()
        / stt;
    let n_fft = n.max(min_fft_len).next_power_of_two();
    let fft = FftPlanner::<f64>::new().plan_fft_forward(n_fft);
    let mut spectra = Vec::with_capacity(3);
    for axis in 0..3 {
        let mut buf = vec![Complex::new(0.0, 0.0); n_fft];
        for (i, p) in window.iter().enumerate() {
            let mut d = *p - mean - (i as f64 - tm) * slope;
            d -= d.dot(along) * along;
            let w = 0.5 - 0.5 * (std::f64::consts::TAU * (i as f64 + 0.5) / n as f64).cos();
            buf[i] = Complex::new(d[axis] * w, 0.0);
        }
        fft.process(&mut buf);
        spectra.push(buf);
    }
    let df = fps / n_fft as f64;
    let lo = (band.0 / df).ceil() as usize;
    let hi = ((band.1 / df).floor() as usize).min(n_fft / 2);
    let mut c = nalgebra::Matrix3::<f64>::zeros();
    for k in lo..=hi {
        for a in 0..3 {
            for b in 0..3 {
                c[(a, b)] += (spectra[a][k] * spectra[b][k].conj()).re;
            }
        }
    }
    (c.trace() > 0.0 && c.iter().all(|v: &f64| v.is_finite())).then_some(c)
}
