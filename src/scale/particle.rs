//! Particle filter over `(V_SLAM, log10 s)` (thesis eq. 3.20-3.30, natural formulation).
//!
//! State of particle `i`: the trajectory's own speed `V_SLAM,i` (SLAM units/s) and the
//! log-scale `l_i = log10 s_i` (`s` metres per SLAM unit). Per update:
//! - prediction: `l_i += N(0, sigma_drift^2 dt)` (scale drift, `dt` seconds since the last
//!   update, `sigma_drift` in decades per sqrt(s)); `V_SLAM,i = V_SLAM (1 + N(0, r^2))` around
//!   the measured SLAM speed with relative spread `r = sigma_vslam_rel`;
//! - likelihood of the walking speed `V_walk = alpha f^beta H`, evaluated in log space so that
//!   the geometric mean is unbiased: `w_i ~ exp(-(log10 V_walk - l_i - log10 V_SLAM,i)^2 /
//!   (2 sigma_l^2))` with `sigma_l = sigma_Vwalk / (V_walk ln 10)` (the first-order image of
//!   `sigma_Vwalk` at the measured speed; a Gaussian in `V` with a prior uniform in `log s`
//!   biases the geometric mean low by about `(sigma_Vwalk / V)^2`, ~3 % here);
//! - consistency test on the predictive distribution: with `m`, `v` the mean and variance of
//!   the predicted `l_i`, the measured log-ratio `log10(V_walk / V_SLAM)` must lie within
//!   `consistency_sigmas` standard deviations `sqrt(v + sigma_l^2 + (r / ln 10)^2)` of `m`
//!   (and some particle within `consistency_sigmas sigma_l`); otherwise the measurement is
//!   rejected (no update). Testing only the best of 5000 particles would let a false step
//!   detection (a standstill wobble of the estimate read as slow steps) drag the whole
//!   posterior onto the prior's tail. After `max_inconsistent` rejections in a row whose
//!   log-ratios agree with each other (spread within `consistency_sigmas sigma_l`) the
//!   filter re-initialises around their mean: the scale really jumped;
//! - 95 % tail trimming: particles outside the central 95 % of the weighted distribution of
//!   `l` get weight 0;
//! - multinomial resampling; the estimate is the geometric mean of the scale,
//!   `s = 10^mean(l)`, over the resampled particles.
//!
//! Initialisation: `l_i ~ N(prior_log10, sigma_0^2)` (thesis `sigma_0 = 1` decade).

use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;

use super::{check_param, ScaleError};

/// Settings of the particle filter (defaults: the thesis' values).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ParticleConfig {
    /// Number of particles (thesis: 5000).
    pub particles: usize,
    /// Prior standard deviation of `log10 s`, decades (thesis: 1).
    pub sigma0: f64,
    /// Prior mean of `log10 s` (0: SLAM units taken as metres).
    pub prior_log10: f64,
    /// Scale drift, decades of `log10 s` per sqrt(second) (thesis: 0.1 per update of 1 s).
    pub sigma_drift: f64,
    /// Standard deviation of the walking-speed model, m/s (thesis: 0.2).
    pub sigma_vwalk: f64,
    /// Relative spread of `V_SLAM` around its measurement.
    pub sigma_vslam_rel: f64,
    /// Central probability mass kept by the tail trimming (thesis: 0.95).
    pub keep_mass: f64,
    /// A measurement is inconsistent when its log-ratio lies further than this many standard
    /// deviations from the predicted log-scales, or this many `sigma_l` from every particle.
    pub consistency_sigmas: f64,
    /// Re-initialise after this many inconsistent measurements in a row that agree with each
    /// other (their log-ratios within `consistency_sigmas sigma_l`).
    pub max_inconsistent: usize,
}

impl Default for ParticleConfig {
    fn default() -> Self {
        ParticleConfig {
            particles: 5000,
            sigma0: 1.0,
            prior_log10: 0.0,
            sigma_drift: 0.1,
            sigma_vwalk: 0.2,
            sigma_vslam_rel: 0.05,
            keep_mass: 0.95,
            consistency_sigmas: 3.0,
            max_inconsistent: 3,
        }
    }
}

impl ParticleConfig {
    /// Checks the ranges of the settings.
    pub fn validate(&self) -> Result<(), ScaleError> {
        check_param("particles", self.particles >= 10, || {
            format!("{} must be >= 10", self.particles)
        })?;
        for (name, v) in [
            ("sigma0", self.sigma0),
            ("sigma_vwalk", self.sigma_vwalk),
            ("consistency_sigmas", self.consistency_sigmas),
        ] {
            check_param(name, v.is_finite() && v > 0.0, || {
                format!("{v} must be > 0")
            })?;
        }
        for (name, v) in [
            ("sigma_drift", self.sigma_drift),
            ("sigma_vslam_rel", self.sigma_vslam_rel),
        ] {
            check_param(name, v.is_finite() && v >= 0.0, || {
                format!("{v} must be >= 0")
            })?;
        }
        check_param("max_inconsistent", self.max_inconsistent >= 1, || {
            format!("{} must be >= 1", self.max_inconsistent)
        })?;
        check_param("prior_log10", self.prior_log10.is_finite(), || {
            "must be finite".into()
        })?;
        check_param(
            "keep_mass",
            self.keep_mass > 0.0 && self.keep_mass <= 1.0,
            || format!("{} must be in (0, 1]", self.keep_mass),
        )
    }
}

/// Outcome of one filter update.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct FilterUpdate {
    /// Scale estimate after the update (geometric mean), metres per SLAM unit.
    pub scale: f64,
    /// Standard deviation of `log10 s` over the particles, decades.
    pub log10_std: f64,
    /// Whether the measurement passed the consistency test and was used.
    pub consistent: bool,
    /// Whether the filter was (re-)initialised by this measurement.
    pub initialised: bool,
}

/// The particle filter (seeded, deterministic).
#[derive(Clone, Debug)]
pub struct ScaleFilter {
    cfg: ParticleConfig,
    rng: Pcg64,
    v_slam: Vec<f64>,
    log_scale: Vec<f64>,
    initialised: bool,
    /// Log-ratios `log10(V_walk / V_SLAM)` and `sigma_l` of the current run of rejections.
    rejected: Vec<(f64, f64)>,
}

/// A standard normal sample by Box-Muller (keeps the dependency list short).
pub fn standard_normal<R: Rng>(rng: &mut R) -> f64 {
    let u1: f64 = rng.random::<f64>().max(1e-300);
    let u2: f64 = rng.random::<f64>();
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}

fn normal<R: Rng>(rng: &mut R) -> f64 {
    standard_normal(rng)
}

impl ScaleFilter {
    /// A filter with `cfg`, seeded with `seed`.
    pub fn new(cfg: ParticleConfig, seed: u64) -> Result<ScaleFilter, ScaleError> {
        cfg.validate()?;
        Ok(ScaleFilter {
            rng: Pcg64::seed_from_u64(seed),
            v_slam: Vec::new(),
            log_scale: Vec::new(),
            initialised: false,
            rejected: Vec::new(),
            cfg,
        })
    }

    /// The settings.
    pub fn config(&self) -> &ParticleConfig {
        &self.cfg
    }

    /// Current scale estimate (geometric mean), `None` before the first update.
    pub fn estimate(&self) -> Option<f64> {
        if !self.initialised {
            return None;
        }
        let n = self.log_scale.len() as f64;
        Some(10f64.powf(self.log_scale.iter().sum::<f64>() / n))
    }

    /// Mean and variance of the particles' `log10 s`.
    fn moments(&self) -> (f64, f64) {
        let n = self.log_scale.len() as f64;
        let m = self.log_scale.iter().sum::<f64>() / n;
        (
            m,
            self.log_scale.iter().map(|l| (l - m).powi(2)).sum::<f64>() / n,
        )
    }

    fn spread(&self) -> f64 {
        self.moments().1.sqrt()
    }

    fn initialise(&mut self, center: f64) {
        let n = self.cfg.particles;
        self.log_scale = (0..n)
            .map(|_| center + self.cfg.sigma0 * normal(&mut self.rng))
            .collect();
        self.v_slam = vec![0.0; n];
        self.initialised = true;
        self.rejected.clear();
    }

    /// One update with the measured SLAM speed `v_slam` (SLAM units/s, > 0), the walking speed
    /// `v_walk` (m/s, from the step frequency) and the time `dt` (s) since the last update.
    pub fn update(
        &mut self,
        v_slam: f64,
        v_walk: f64,
        dt: f64,
    ) -> Result<FilterUpdate, ScaleError> {
        if !(v_slam.is_finite() && v_slam > 0.0 && v_walk.is_finite() && v_walk > 0.0) {
            return Err(ScaleError::InvalidParameter {
                name: "speeds",
                why: format!("V_SLAM {v_slam} and V_walk {v_walk} must be finite and > 0"),
            });
        }
        let dt = if dt.is_finite() { dt.max(0.0) } else { 0.0 };
        let mut initialised = false;
        if !self.initialised {
            self.initialise(self.cfg.prior_log10);
            initialised = true;
        }
        let n = self.log_scale.len();
        let drift = self.cfg.sigma_drift * dt.sqrt();
        for i in 0..n {
            self.log_scale[i] += drift * normal(&mut self.rng);
            self.v_slam[i] =
                (v_slam * (1.0 + self.cfg.sigma_vslam_rel * normal(&mut self.rng))).max(1e-12);
        }
        let sigma_l = self.cfg.sigma_vwalk / (v_walk * std::f64::consts::LN_10);
        let inv2 = 0.5 / sigma_l.powi(2);
        let lw = v_walk.log10();
        let loglik = |l: f64, v: f64| -> f64 {
            let e = lw - l - v.log10();
            -e * e * inv2
        };
        let mut w: Vec<f64> = (0..n)
            .map(|i| loglik(self.log_scale[i], self.v_slam[i]))
            .collect();
        let best = w.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
        let k = self.cfg.consistency_sigmas;
        let gate = -0.5 * k.powi(2);
        let ratio = (v_walk / v_slam).log10();
        let (mean, var) = self.moments();
        let noise = sigma_l.powi(2) + (self.cfg.sigma_vslam_rel / std::f64::consts::LN_10).powi(2);
        let predicted = (ratio - mean).abs() <= k * (var + noise).sqrt();
        if best < gate || !predicted {
            self.rejected.push((ratio, sigma_l));
            let m = self.cfg.max_inconsistent;
            if self.rejected.len() >= m {
                let last = &self.rejected[self.rejected.len() - m..];
                let lo = last.iter().map(|r| r.0).fold(f64::INFINITY, f64::min);
                let hi = last.iter().map(|r| r.0).fold(f64::NEG_INFINITY, f64::max);
                let sig = last.iter().map(|r| r.1).fold(0.0, f64::max);
                if hi - lo <= k * sig {
                    // The scale jumped (or the prior was far off), and the rejected
                    // measurements agree: restart around them.
                    let center = last.iter().map(|r| r.0).sum::<f64>() / m as f64;
                    self.initialise(center);
                    return self.update(v_slam, v_walk, 0.0).map(|mut u| {
                        u.initialised = true;
                        u
                    });
                }
            }
            return Ok(FilterUpdate {
                scale: self.estimate().unwrap_or(1.0),
                log10_std: self.spread(),
                consistent: false,
                initialised,
            });
        }
        self.rejected.clear();
        for v in w.iter_mut() {
            *v = (*v - best).exp();
        }
        // Tail trimming on the weighted distribution of log-scales.
        let mut order: Vec<usize> = (0..n).collect();
        order.sort_by(|&a, &b| self.log_scale[a].total_cmp(&self.log_scale[b]));
        let total: f64 = w.iter().sum();
        let tail = 0.5 * (1.0 - self.cfg.keep_mass) * total;
        let mut acc = 0.0;
        for &i in &order {
            let before = acc;
            acc += w[i];
            if acc <= tail || before >= total - tail {
                w[i] = 0.0;
            }
        }
        let kept: f64 = w.iter().sum();
        if !(kept > 0.0) {
            // Everything trimmed (a degenerate, single-particle posterior): keep weights as is.
            for (i, v) in w.iter_mut().enumerate() {
                *v = (loglik(self.log_scale[i], self.v_slam[i]) - best).exp();
            }
        }
        // Multinomial resampling (sorted uniforms against the cumulative weights).
        let mut cum = Vec::with_capacity(n);
        let mut s = 0.0;
        for v in &w {
            s += v;
            cum.push(s);
        }
        let mut u: Vec<f64> = (0..n).map(|_| self.rng.random::<f64>() * s).collect();
        u.sort_by(f64::total_cmp);
        let mut new_l = Vec::with_capacity(n);
        let mut new_v = Vec::with_capacity(n);
        let mut j = 0;
        for x in u {
            while j + 1 < n && cum[j] < x {
                j += 1;
            }
            new_l.push(self.log_scale[j]);
            new_v.push(self.v_slam[j]);
        }
        self.log_scale = new_l;
        self.v_slam = new_v;
        Ok(FilterUpdate {
            scale: self.estimate().unwrap_or(1.0),
            log10_std: self.spread(),
            consistent: true,
            initialised,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn converges_to_constant_scale() {
        let mut f = ScaleFilter::new(ParticleConfig::default(), 7).unwrap();
        let truth = 2.7; // metres per SLAM unit
        let mut rng = Pcg64::seed_from_u64(1);
        let mut last = None;
        for _ in 0..40 {
            let v_metric = 1.2 + 0.3 * rng.random::<f64>();
            let v_walk = v_metric * (1.0 + 0.05 * normal(&mut rng));
            last = Some(f.update(v_metric / truth, v_walk, 1.0).unwrap());
        }
        let u = last.unwrap();
        assert!((u.scale / truth - 1.0).abs() < 0.15, "{u:?}");
        assert!(f.update(-1.0, 1.0, 1.0).is_err());
    }

    fn converged(truth: f64) -> ScaleFilter {
        let mut f = ScaleFilter::new(ParticleConfig::default(), 3).unwrap();
        for _ in 0..20 {
            f.update(1.3 / truth, 1.3, 1.0).unwrap();
        }
        f
    }

    #[test]
    fn a_lone_outlier_is_rejected_and_moves_nothing() {
        // A standstill wobble read as slow steps: V_walk 0.64 m/s from 1.1 Hz against a tiny
        // SLAM speed, i.e. a scale 7.5x the truth, four seconds after the last update.
        let mut f = converged(3.6);
        let before = f.estimate().unwrap();
        let u = f.update(0.024, 0.64, 4.0).unwrap();
        assert!(!u.consistent, "{u:?}");
        // Only the drift of the prediction step moves it.
        assert!((f.estimate().unwrap() / before - 1.0).abs() < 0.05);
        // Good measurements are still used afterwards.
        let u = f.update(1.3 / 3.6, 1.3, 1.0).unwrap();
        assert!(u.consistent && (u.scale / 3.6 - 1.0).abs() < 0.1, "{u:?}");
    }

    #[test]
    fn agreeing_rejections_reinitialise_scattered_ones_do_not() {
        let mut f = converged(3.6);
        // Scattered outliers (implied scales 30, 0.3, 30, 0.3): never a restart.
        for (i, v) in [0.043, 4.3, 0.043, 4.3].into_iter().enumerate() {
            let u = f.update(v, 1.3, 1.0).unwrap();
            assert!(!u.consistent && !u.initialised, "{i}: {u:?}");
        }
        assert!((f.estimate().unwrap() / 3.6 - 1.0).abs() < 0.15);
        // The scale really jumped to 40 (a decade): three agreeing rejections restart the
        // filter there.
        let mut f = converged(3.6);
        let mut updates = Vec::new();
        for _ in 0..3 {
            updates.push(f.update(1.3 / 40.0, 1.3, 1.0).unwrap());
        }
        assert!(
            !updates[0].consistent && !updates[1].consistent,
            "{updates:?}"
        );
        let u = updates[2];
        assert!(
            u.initialised && (u.scale / 40.0 - 1.0).abs() < 0.15,
            "{u:?}"
        );
    }
}
