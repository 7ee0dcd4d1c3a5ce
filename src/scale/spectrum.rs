//! Step frequency from the vertical oscillation of a walking camera (thesis eq. 3.15-3.19).
//!
//! The vertical coordinate of the camera (SLAM units) has its offset removed, passes a
//! second-order Butterworth high-pass at 0.7 Hz (removing slow height changes, stair ramps and
//! drift), and each analysis window is Hann-windowed, zero-padded and transformed by FFT
//! (`rustfft`). The one-sided power spectral density is normalised so that Parseval holds:
//! `sum_k PSD_k df = mean square` of the window. The step frequency is the PSD peak in the
//! feasible band (1-3 Hz), refined by a parabola through the log-PSD around the peak bin; a
//! peak with a comparable one at exactly twice its frequency is taken for the stride (half the
//! step frequency) and the one at twice it for the step (`SpectrumConfig::stride_ratio`).
//!
//! Walking / standing (3.18-3.19): the walker is taken to walk when (a) the power around the
//! peak (`P_peak`, the Hann main lobe `f_p +- 2/T`) is a fair share of the whole high-passed
//! power (`P_peak / P_total >= min_concentration`, scale-free), and (b) once a metric scale `s`
//! is known, the metric amplitude `A = s sqrt(2 P_peak)` of the oscillation (Parseval: a sine of
//! amplitude `A` has mean square `A^2 / 2`) lies within `[A_z-, A_z+]`.

use std::f64::consts::{PI, SQRT_2};

use rustfft::{num_complex::Complex, FftPlanner};

use super::{check_param, ScaleError};

/// Settings of the spectral analysis.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SpectrumConfig {
    /// Cut-off of the second-order high-pass filter, Hz (thesis: 0.7).
    pub highpass_hz: f64,
    /// Feasible step-frequency band, Hz (thesis: 1-3).
    pub band: (f64, f64),
    /// Minimum share of the high-passed power at or above the band's bottom that lies in the
    /// peak's main lobe, to call it walking.
    pub min_concentration: f64,
    /// Bounds `(A_z-, A_z+)` on the metric vertical oscillation amplitude while walking, metres.
    pub amplitude_bounds: (f64, f64),
    /// Minimum FFT length after zero padding (a power of two is used).
    pub min_fft_len: usize,
    /// Peaks in the band with at least this share of the strongest peak's density are
    /// candidates for the step frequency when a predicted frequency is known
    /// ([`StepAnalysis::analyze_with_hint`]).
    #[serde(default = "default_candidate_ratio")]
    pub candidate_ratio: f64,
    /// Stride-aware peak choice: when the band also holds a PSD peak at twice the chosen
    /// one's frequency (within [`Self::stride_tolerance_hz`]) with at least this share of its
    /// density, the chosen peak is taken for the stride (half the step frequency: one leg
    /// lifting the body more than the other, as on stairs) and the step frequency is the one
    /// at twice it. 0 turns the choice off. A harmonic of a step oscillation (the steps of a
    /// staircase, at most a quarter of the fundamental's density) stays below the default.
    #[serde(default = "default_stride_ratio")]
    pub stride_ratio: f64,
    /// Largest difference between the second peak's frequency and twice the first one's for
    /// the stride-aware choice, Hz (two refined peak frequencies, so a few times the error of
    /// one; well under the main lobe, so an unrelated peak near twice the frequency is not
    /// taken).
    #[serde(default = "default_stride_tolerance")]
    pub stride_tolerance_hz: f64,
}

fn default_candidate_ratio() -> f64 {
    0.5
}

fn default_stride_ratio() -> f64 {
    0.4
}

fn default_stride_tolerance() -> f64 {
    0.08
}

impl Default for SpectrumConfig {
    fn default() -> Self {
        SpectrumConfig {
            highpass_hz: 0.7,
            band: (1.0, 3.0),
            min_concentration: 0.35,
            amplitude_bounds: (0.005, 0.10),
            min_fft_len: 4096,
            candidate_ratio: default_candidate_ratio(),
            stride_ratio: default_stride_ratio(),
            stride_tolerance_hz: default_stride_tolerance(),
        }
    }
}

impl SpectrumConfig {
    /// Checks the ranges of the settings.
    pub fn validate(&self) -> Result<(), ScaleError> {
        check_param(
            "highpass_hz",
            self.highpass_hz > 0.0 && self.highpass_hz.is_finite(),
            || format!("{} Hz must be > 0", self.highpass_hz),
        )?;
        check_param(
            "band",
            self.band.0 > 0.0 && self.band.1 > self.band.0 && self.band.1.is_finite(),
            || format!("{:?} must be 0 < low < high", self.band),
        )?;
        check_param(
            "amplitude_bounds",
            self.amplitude_bounds.0 >= 0.0 && self.amplitude_bounds.1 > self.amplitude_bounds.0,
            || format!("{:?} must be 0 <= low < high", self.amplitude_bounds),
        )?;
        check_param(
            "candidate_ratio",
            self.candidate_ratio > 0.0 && self.candidate_ratio <= 1.0,
            || format!("{} must be in (0, 1]", self.candidate_ratio),
        )?;
        check_param(
            "stride_ratio",
            (0.0..=1.0).contains(&self.stride_ratio),
            || format!("{} must be in [0, 1]", self.stride_ratio),
        )?;
        check_param(
            "stride_tolerance_hz",
            self.stride_tolerance_hz.is_finite() && self.stride_tolerance_hz > 0.0,
            || format!("{} Hz must be > 0", self.stride_tolerance_hz),
        )?;
        check_param(
            "min_concentration",
            (0.0..=1.0).contains(&self.min_concentration),
            || format!("{} must be in [0, 1]", self.min_concentration),
        )
    }
}

/// A causal second-order Butterworth high-pass filter (bilinear transform, pre-warped).
#[derive(Clone, Debug)]
pub struct HighPass {
    b: [f64; 3],
    a: [f64; 2],
    x: [f64; 2],
    y: [f64; 2],
}

impl HighPass {
    /// A filter with cut-off `cutoff_hz` for samples at `sample_rate_hz`.
    pub fn new(cutoff_hz: f64, sample_rate_hz: f64) -> Result<HighPass, ScaleError> {
        check_param(
            "cutoff_hz",
            cutoff_hz > 0.0 && sample_rate_hz.is_finite() && cutoff_hz < 0.5 * sample_rate_hz,
            || format!("{cutoff_hz} Hz must be in (0, {}) Hz", 0.5 * sample_rate_hz),
        )?;
        let k = (PI * cutoff_hz / sample_rate_hz).tan();
        let norm = 1.0 / (1.0 + SQRT_2 * k + k * k);
        Ok(HighPass {
            b: [norm, -2.0 * norm, norm],
            a: [
                2.0 * (k * k - 1.0) * norm,
                (1.0 - SQRT_2 * k + k * k) * norm,
            ],
            x: [0.0; 2],
            y: [0.0; 2],
        })
    }
    /// Filters one sample.
    pub fn step(&mut self, x: f64) -> f64 {
        let y = self.b[0] * x + self.b[1] * self.x[0] + self.b[2] * self.x[1]
            - self.a[0] * self.y[0]
            - self.a[1] * self.y[1];
        self.x = [x, self.x[0]];
        self.y = [y, self.y[0]];
        y
    }
    /// Removes the offset (the first sample) and filters a whole signal from rest.
    pub fn filter_signal(
        cutoff_hz: f64,
        sample_rate_hz: f64,
        signal: &[f64],
    ) -> Result<Vec<f64>, ScaleError> {
        let mut f = HighPass::new(cutoff_hz, sample_rate_hz)?;
        let x0 = signal.first().copied().unwrap_or(0.0);
        Ok(signal.iter().map(|&x| f.step(x - x0)).collect())
    }
}

/// One-sided power spectral density of `signal` (Hann window, mean removed, zero-padded to
/// `n_fft >= len`, a power of two): returns `(df Hz, psd)` with `psd[k]` at `k df` in
/// units^2 / Hz, normalised so that `sum psd df` is the window's mean square.
pub fn power_spectral_density(
    signal: &[f64],
    sample_rate_hz: f64,
    min_fft_len: usize,
) -> (f64, Vec<f64>) {
    let n = signal.len();
    let n_fft = n.max(min_fft_len).max(2).next_power_of_two();
    if n == 0 {
        return (sample_rate_hz / n_fft as f64, vec![0.0; n_fft / 2 + 1]);
    }
    let mean = signal.iter().sum::<f64>() / n as f64;
    let w: Vec<f64> = (0..n)
        .map(|i| 0.5 - 0.5 * (2.0 * PI * (i as f64 + 0.5) / n as f64).cos())
        .collect();
    let w2: f64 = w.iter().map(|v| v * v).sum::<f64>().max(1e-300);
    let mut buf: Vec<Complex<f64>> = vec![Complex::new(0.0, 0.0); n_fft];
    for i in 0..n {
        buf[i] = Complex::new((signal[i] - mean) * w[i], 0.0);
    }
    FftPlanner::<f64>::new()
        .plan_fft_forward(n_fft)
        .process(&mut buf);
    let norm = 1.0 / (sample_rate_hz * w2);
    let half = n_fft / 2;
    let psd = (0..=half)
        .map(|k| {
            let p = buf[k].norm_sqr() * norm;
            if k == 0 || k == half {
                p
            } else {
                2.0 * p
            }
        })
        .collect();
    (sample_rate_hz / n_fft as f64, psd)
}

/// Spectral analysis of one window of the high-passed vertical signal.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct StepAnalysis {
    /// Peak frequency in the feasible band, Hz (steps per second).
    pub frequency: f64,
    /// Power in the peak's main lobe (`f +- 2/T`), SLAM units^2.
    pub peak_power: f64,
    /// Power in the feasible band, SLAM units^2.
    pub band_power: f64,
    /// Whole power of the window (mean square), SLAM units^2.
    pub total_power: f64,
    /// Oscillation amplitude `sqrt(2 peak_power)`, SLAM units.
    pub amplitude: f64,
    /// `peak_power` over the power from the band's bottom up to the Nyquist frequency, in
    /// [0, 1]; 0 when the band's maximum is not a local maximum of the PSD (at a band edge
    /// with the PSD rising beyond it: no gait peak).
    pub concentration: f64,
    /// Expected standard deviation of `frequency`, Hz: the Cramer-Rao bound of a sinusoid's
    /// frequency in white noise, `sqrt(3 / (eta N)) / (pi T)`, inflated by the Hann window's
    /// noise bandwidth (1.5), with the signal-to-noise ratio `eta` of the peak's power over
    /// the noise density of the rest of the band (taken as white up to Nyquist); 0 for a
    /// noiseless peak, infinite when the peak has no power.
    #[serde(default)]
    pub frequency_std: f64,
}

impl StepAnalysis {
    /// Analyses one window (`signal`, already high-passed) sampled at `sample_rate_hz`.
    pub fn analyze(
        signal: &[f64],
        sample_rate_hz: f64,
        cfg: &SpectrumConfig,
    ) -> Result<StepAnalysis, ScaleError> {
        Self::analyze_with_hint(signal, sample_rate_hz, cfg, None)
    }

    /// Like [`Self::analyze`], but when the band holds several PSD peaks of comparable power
    /// (local maxima with at least `cfg.candidate_ratio` of the strongest one's density), the
    /// one closest to `hint` (Hz, in ratio) is taken. The hint is the step frequency the
    /// walking model predicts from the current scale and the trajectory's speed: a monocular
    /// estimate can carry a wobble of its own near 1 Hz as strong as the gait peak.
    pub fn analyze_with_hint(
        signal: &[f64],
        sample_rate_hz: f64,
        cfg: &SpectrumConfig,
        hint: Option<f64>,
    ) -> Result<StepAnalysis, ScaleError> {
        cfg.validate()?;
        check_param(
            "sample_rate_hz",
            sample_rate_hz.is_finite() && sample_rate_hz > 2.0 * cfg.band.1,
            || {
                format!(
                    "{sample_rate_hz} Hz must exceed twice the band's top {} Hz",
                    cfg.band.1
                )
            },
        )?;
        if signal.len() < 8 {
            return Err(ScaleError::TooShort {
                have: signal.len(),
                seconds: signal.len() as f64 / sample_rate_hz,
                need: "8 samples per window".into(),
            });
        }
        if signal.iter().any(|v| !v.is_finite()) {
            return Err(ScaleError::NonFinite("vertical signal".into()));
        }
        let (df, psd) = power_spectral_density(signal, sample_rate_hz, cfg.min_fft_len);
        let bin = |f: f64| ((f / df).round().max(0.0) as usize).min(psd.len() - 1);
        let (lo, hi) = (bin(cfg.band.0), bin(cfg.band.1));
        let mut kmax = lo;
        for k in lo..=hi {
            if psd[k] > psd[kmax] {
                kmax = k;
            }
        }
        let peaks: Vec<usize> = (lo.max(1)..=hi.min(psd.len() - 2))
            .filter(|&k| psd[k] > psd[k - 1] && psd[k] >= psd[k + 1])
            .collect();
        if let Some(fh) = hint.filter(|f| f.is_finite() && *f > 0.0) {
            let strongest = peaks.iter().map(|&k| psd[k]).fold(0.0, f64::max);
            let dist = |k: usize| ((k as f64 * df) / fh).ln().abs();
            if let Some(&k) = peaks
                .iter()
                .filter(|&&k| psd[k] >= cfg.candidate_ratio * strongest)
                .min_by(|&&a, &&b| dist(a).total_cmp(&dist(b)))
            {
                kmax = k;
            }
        }
        // Parabolic refinement on the log PSD.
        let refine = |k: usize| -> f64 {
            if k > 0 && k + 1 < psd.len() {
                let (a, b, c) = (
                    psd[k - 1].max(1e-300).ln(),
                    psd[k].max(1e-300).ln(),
                    psd[k + 1].max(1e-300).ln(),
                );
                let den = a - 2.0 * b + c;
                if den < 0.0 {
                    return (k as f64 + (0.5 * (a - c) / den).clamp(-0.5, 0.5)) * df;
                }
            }
            k as f64 * df
        };
        // The stride and the step are locked at 1 : 2, so a peak at exactly twice the chosen
        // one means the chosen one is the stride; the walking model's hint cannot tell them
        // apart while the scale is still unknown or wrong by the ratio of their speeds.
        if cfg.stride_ratio > 0.0 {
            let double = 2.0 * refine(kmax);
            if let Some(&k) = peaks
                .iter()
                .filter(|&&k| {
                    psd[k] >= cfg.stride_ratio * psd[kmax]
                        && (refine(k) - double).abs() <= cfg.stride_tolerance_hz
                })
                .max_by(|&&a, &&b| psd[a].total_cmp(&psd[b]))
            {
                kmax = k;
            }
        }
        // A gait peak is a local maximum of the PSD; at a band edge, with the PSD still rising
        // outside the band (the 1/f^2 tail of a drifting estimate at the bottom), there is none.
        let local_max = (kmax == 0 || psd[kmax] > psd[kmax - 1])
            && (kmax + 1 >= psd.len() || psd[kmax] > psd[kmax + 1]);
        let frequency = refine(kmax);
        let t = signal.len() as f64 / sample_rate_hz;
        let sum =
            |f0: f64, f1: f64| -> f64 { (bin(f0)..=bin(f1)).map(|k| psd[k]).sum::<f64>() * df };
        let lobe = 2.0 / t;
        let peak_power = sum((frequency - lobe).max(0.0), frequency + lobe);
        let band_power = sum(cfg.band.0, cfg.band.1);
        let total_power = psd.iter().sum::<f64>() * df;
        // Share of the peak in the power from the band's bottom up: what the second-order
        // high-pass leaves below the band (slow drift of a monocular estimate, up to ~75 % of
        // a 4 s window's power with the EKF) says nothing about steps; broadband noise above
        // it (standing still) spreads the power and keeps the share low.
        let above = sum(cfg.band.0, sample_rate_hz / 2.0);
        let concentration = if above > 0.0 && local_max {
            (peak_power / above).clamp(0.0, 1.0)
        } else {
            0.0
        };
        // Noise density of the band outside the peak's main lobe, then the bound.
        let width = (cfg.band.1 - cfg.band.0 - 2.0 * lobe).max(df);
        let noise_variance = (band_power - peak_power).max(0.0) / width * 0.5 * sample_rate_hz;
        let eta = peak_power / noise_variance;
        let frequency_std = if eta.is_finite() && eta > 0.0 {
            (4.5 / (eta * signal.len() as f64)).sqrt() / (PI * t)
        } else if peak_power > 0.0 {
            0.0
        } else {
            f64::INFINITY
        };
        Ok(StepAnalysis {
            frequency,
            peak_power,
            band_power,
            total_power,
            amplitude: (2.0 * peak_power).sqrt(),
            concentration,
            frequency_std,
        })
    }

    /// Walking detection: the spectral concentration test, plus the Parseval amplitude bounds
    /// `A_z- <= s sqrt(2 P_peak) <= A_z+` when a metric `scale` (metres per SLAM unit) is known.
    pub fn is_walking(&self, cfg: &SpectrumConfig, scale: Option<f64>) -> bool {
        if !(self.concentration >= cfg.min_concentration) {
            return false;
        }
        match scale {
            Some(s) => {
                let a = s * self.amplitude;
                a >= cfg.amplitude_bounds.0 && a <= cfg.amplitude_bounds.1
            }
            None => self.amplitude > 0.0,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn highpass_removes_ramp_and_keeps_fast_sine() {
        let fs = 30.0;
        let x: Vec<f64> = (0..600)
            .map(|i| {
                let t = i as f64 / fs;
                0.3 * t + 0.02 * (2.0 * PI * 2.0 * t).sin()
            })
            .collect();
        let y = HighPass::filter_signal(0.7, fs, &x).unwrap();
        let tail = &y[300..];
        let max = tail.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        assert!(
            max > 0.017 && max < 0.023,
            "2 Hz amplitude after high-pass: {max}"
        );
        let mean = tail.iter().sum::<f64>() / tail.len() as f64;
        assert!(mean.abs() < 1e-3, "ramp left a DC offset {mean}");
    }

    #[test]
    fn hint_chooses_among_comparable_peaks_only() {
        let fs = 30.0;
        let sig = |a2: f64| -> Vec<f64> {
            (0..120)
                .map(|i| {
                    let t = i as f64 / fs;
                    (2.0 * PI * 1.1 * t).sin() + a2 * (2.0 * PI * 2.0 * t + 0.3).sin()
                })
                .collect()
        };
        let cfg = SpectrumConfig::default();
        let f = |x: &[f64], h: Option<f64>| {
            StepAnalysis::analyze_with_hint(x, fs, &cfg, h)
                .unwrap()
                .frequency
        };
        let two = sig(0.9);
        assert!((f(&two, None) - 1.1).abs() < 0.05, "{}", f(&two, None));
        assert!(
            (f(&two, Some(1.9)) - 2.0).abs() < 0.05,
            "{}",
            f(&two, Some(1.9))
        );
        assert!((f(&two, Some(1.2)) - 1.1).abs() < 0.05);
        // A weak second peak (power 0.09 of the first) is never chosen.
        let weak = sig(0.3);
        assert!(
            (f(&weak, Some(2.0)) - 1.1).abs() < 0.05,
            "{}",
            f(&weak, Some(2.0))
        );
    }

    #[test]
    fn stride_peak_gives_the_step_at_twice_it() {
        let fs = 30.0;
        let sig = |f1: f64, a2: f64, f2: f64| -> Vec<f64> {
            (0..120)
                .map(|i| {
                    let t = i as f64 / fs;
                    0.05 * (2.0 * PI * f1 * t).sin() + a2 * (2.0 * PI * f2 * t + 0.4).sin()
                })
                .collect()
        };
        let on = SpectrumConfig::default();
        let off = SpectrumConfig {
            stride_ratio: 0.0,
            ..on.clone()
        };
        let f = |x: &[f64], c: &SpectrumConfig, h: Option<f64>| {
            StepAnalysis::analyze_with_hint(x, fs, c, h)
                .unwrap()
                .frequency
        };
        // The stride (1.1 Hz) stronger than the step (2.2 Hz), as on stairs with unequal legs.
        let stairs = sig(1.1, 0.035, 2.2);
        assert!((f(&stairs, &off, None) - 1.1).abs() < 0.03);
        assert!((f(&stairs, &on, None) - 2.2).abs() < 0.03);
        // Also when a wrong scale predicts the stride.
        assert!((f(&stairs, &on, Some(1.1)) - 2.2).abs() < 0.03);
        // A harmonic of the step at a quarter of its density is not the step.
        let harmonic = sig(1.2, 0.025, 2.4);
        assert!((f(&harmonic, &on, None) - 1.2).abs() < 0.03);
        // A comparable peak near, but not at, twice the frequency is not taken for the step.
        let near = sig(1.1, 0.045, 2.0);
        assert!((f(&near, &on, None) - 1.1).abs() < 0.03);
    }

    #[test]
    fn parseval_holds() {
        let fs = 30.0;
        let x: Vec<f64> = (0..240)
            .map(|i| 0.03 * (2.0 * PI * 1.7 * i as f64 / fs).sin())
            .collect();
        let (df, psd) = power_spectral_density(&x, fs, 4096);
        let p = psd.iter().sum::<f64>() * df;
        assert!(
            (p - 0.03f64.powi(2) / 2.0).abs() < 0.05 * 0.00045,
            "power {p}"
        );
    }
}
