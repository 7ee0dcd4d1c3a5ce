//! Robust estimators for IRLS (thesis eq. 6.14-6.17 and 4.25): weights, scale estimation by
//! maximum likelihood or MAD, and the Student-t degrees of freedom.
//!
//! Residuals are in their natural units (intensity levels for the photometric term, 1/m or m
//! for the geometric term); a scale `sigma` has the same unit.

/// The robust loss used to weight residuals.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "lowercase")]
#[repr(u32)]
pub enum Estimator {
    /// Plain least squares (weight 1). JSON: `"leastsquares"` (or `"least-squares"`, as on
    /// the command line).
    #[serde(alias = "least-squares")]
    LeastSquares = 0,
    /// Huber with k = 1.345 (in units of sigma).
    Huber = 1,
    /// Tukey biweight with c = 4.685.
    Tukey = 2,
    /// Student-t with estimated degrees of freedom (the thesis' default).
    Student = 3,
}

/// [`Estimator`] codes as the kernels receive them (`WarpParams::estimator`).
const HUBER: u32 = Estimator::Huber as u32;
const TUKEY: u32 = Estimator::Tukey as u32;
const STUDENT: u32 = Estimator::Student as u32;

/// Huber's tuning constant (95 % efficiency at the Gaussian).
pub const HUBER_K: f32 = 1.345;
/// Tukey's tuning constant (95 % efficiency at the Gaussian).
pub const TUKEY_C: f32 = 4.685;

/// IRLS weight of a normalised residual `z = r / sigma` for the [`Estimator`] whose code is
/// `estimator` (mirror of `robust_weight` in `shaders/odometry.wgsl`; the kernels carry the
/// estimator as `u32`).
#[inline(always)]
pub fn weight(estimator: u32, z: f32, nu: f32) -> f32 {
    match estimator {
        HUBER => {
            let a = z.abs();
            if a <= HUBER_K {
                1.0
            } else {
                HUBER_K / a
            }
        }
        TUKEY => {
            let t = z / TUKEY_C;
            if t.abs() < 1.0 {
                let s = 1.0 - t * t;
                s * s
            } else {
                0.0
            }
        }
        STUDENT => (nu + 1.0) / (nu + z * z),
        _ => 1.0,
    }
}

/// How residual scales are obtained.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "lowercase")]
pub enum ScaleMethod {
    /// Maximum likelihood for the chosen estimator (eq. 4.26, 6.15): quadratic seed, then the
    /// fixed point of the likelihood's stationarity condition `mean(w(r/sigma) (r/sigma)^2) =
    /// 1` of the density `exp(-rho(r/sigma)) / sigma`. For Tukey that density is improper
    /// (rho is bounded), so this is the formal stationary point the thesis' ML definition
    /// gives, not the scale of a distribution.
    Ml,
    /// Median absolute deviation, 1.4826 * MAD (eq. 4.25).
    Mad,
    /// Huber and Tukey: the Gaussian-consistent M-scale `sigma^2 = mean(w r^2) / E[w Z^2]`
    /// (equal to the standard deviation on Gaussian residuals). Student-t and least squares:
    /// the same as [`ScaleMethod::Ml`].
    #[serde(rename = "mscale")]
    #[cfg_attr(feature = "clap", value(name = "mscale"))]
    MScale,
    /// Fixed scales (`sigmaFix`: sigma_I = 5, sigma_W = 0.0025 1/m).
    Fixed,
}

/// Scale (and, for Student-t, degrees of freedom) of one residual population.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct ScaleEstimate {
    /// Scale, in the residual's unit.
    pub sigma: f64,
    /// Student-t degrees of freedom (meaningful for `Estimator::Student`).
    pub nu: f64,
}

/// Relative change of sigma^2 at which the fixed-point scale iteration stops (a scale to
/// 0.05 %; it is re-estimated every Gauss-Newton iteration anyway).
pub const SCALE_TOLERANCE: f64 = 1e-3;

/// Lower bound of the Student-t degrees of freedom search (eq. 6.16).
pub const NU_MIN: f64 = 2.0;
/// Upper bound of the Student-t degrees of freedom search.
pub const NU_MAX: f64 = 10.0;
/// Default degrees of freedom when they are not estimated.
pub const NU_DEFAULT: f64 = 5.0;

/// Digamma function for x > 0 (recurrence to x >= 10, then the asymptotic series).
pub fn digamma(mut x: f64) -> f64 {
    let mut acc = 0.0;
    while x < 10.0 {
        acc -= 1.0 / x;
        x += 1.0;
    }
    let i2 = 1.0 / (x * x);
    acc + x.ln() - 0.5 / x - i2 * (1.0 / 12.0 - i2 * (1.0 / 120.0 - i2 * (1.0 / 252.0)))
}

/// Derivative of the Student-t log-likelihood with respect to nu, given the squared
/// normalised residuals `z2`, divided by n.
fn dlogl_dnu(z2: &[f64], nu: f64) -> f64 {
    let n = z2.len() as f64;
    let mut s = 0.0;
    for &z in z2 {
        s += -(1.0 + z / nu).ln() + (nu + 1.0) * z / (nu * (nu + z));
    }
    0.5 * (digamma(0.5 * (nu + 1.0)) - digamma(0.5 * nu) - 1.0 / nu) + 0.5 * s / n
}

/// At most this many squared residuals enter the degrees-of-freedom likelihood (a systematic
/// sub-sample; nu is a shape parameter and needs far fewer samples than the scale).
pub const NU_MAX_SAMPLES: usize = 2048;

/// Maximum-likelihood degrees of freedom in `[NU_MIN, NU_MAX]`: the root of eq. 6.16's
/// derivative, bracketed in `[2, 10]` and found by regula falsi with the Illinois modification
/// (superlinear; typically 5-7 likelihood evaluations for nu to within 1e-3, where bisection
/// needed 16).
pub fn estimate_nu(z2: &[f64]) -> f64 {
    if z2.is_empty() {
        return NU_DEFAULT;
    }
    let sub: Vec<f64>;
    let z2 = if z2.len() > NU_MAX_SAMPLES {
        let step = z2.len() as f64 / NU_MAX_SAMPLES as f64;
        sub = (0..NU_MAX_SAMPLES)
            .map(|k| z2[(k as f64 * step) as usize])
            .collect();
        &sub[..]
    } else {
        z2
    };
    let (mut lo, mut hi) = (NU_MIN, NU_MAX);
    let (mut flo, mut fhi) = (dlogl_dnu(z2, lo), dlogl_dnu(z2, hi));
    if flo <= 0.0 {
        return lo;
    }
    if fhi >= 0.0 {
        return hi;
    }
    // Invariant: flo > 0 > fhi. `side` remembers which end moved last (Illinois: halve the
    // stale end's value when the same end moves twice, so both ends converge).
    let mut side = 0i8;
    for _ in 0..30 {
        let mid = (lo * fhi - hi * flo) / (fhi - flo);
        let mid = if mid.is_finite() && mid > lo && mid < hi {
            mid
        } else {
            0.5 * (lo + hi)
        };
        let f = dlogl_dnu(z2, mid);
        if f > 0.0 {
            lo = mid;
            flo = f;
            if side == -1 {
                fhi *= 0.5;
            }
            side = -1;
        } else {
            hi = mid;
            fhi = f;
            if side == 1 {
                flo *= 0.5;
            }
            side = 1;
        }
        if hi - lo < 1e-3 || f == 0.0 {
            return mid;
        }
    }
    0.5 * (lo + hi)
}

/// `E[w(Z) Z^2]` for a standard normal Z: the consistency constant of the M-scale (computed
/// once per estimator).
/// The divisor of the fixed-point scale step: 1 for maximum likelihood, `E[w Z^2]` for the
/// Gaussian-consistent M-scale.
fn consistency(estimator: u32, method: ScaleMethod) -> f64 {
    if method == ScaleMethod::MScale {
        gaussian_consistency(estimator)
    } else {
        1.0
    }
}

fn gaussian_consistency(estimator: u32) -> f64 {
    static CACHE: std::sync::OnceLock<[f64; 4]> = std::sync::OnceLock::new();
    CACHE.get_or_init(|| [0, 1, 2, 3].map(gaussian_consistency_uncached))[estimator.min(3) as usize]
}

fn gaussian_consistency_uncached(estimator: u32) -> f64 {
    if estimator != HUBER && estimator != TUKEY {
        return 1.0;
    }
    // Simpson's rule on [-12, 12].
    let n = 4000;
    let h = 24.0 / n as f64;
    let f = |z: f64| {
        let w = f64::from(weight(estimator, z as f32, NU_DEFAULT as f32));
        w * z * z * (-0.5 * z * z).exp() / (2.0 * std::f64::consts::PI).sqrt()
    };
    let mut s = f(-12.0) + f(12.0);
    for i in 1..n {
        let z = -12.0 + i as f64 * h;
        s += if i % 2 == 1 { 4.0 } else { 2.0 } * f(z);
    }
    s * h / 3.0
}

/// Median absolute deviation scale, `1.4826 * median(|r - median(r)|)`.
pub fn mad_sigma(r: &[f64]) -> f64 {
    if r.is_empty() {
        return 0.0;
    }
    let mut v = r.to_vec();
    let mid = v.len() / 2;
    let med = *v.select_nth_unstable_by(mid, f64::total_cmp).1;
    for x in v.iter_mut() {
        *x = (*x - med).abs();
    }
    1.4826 * *v.select_nth_unstable_by(mid, f64::total_cmp).1
}

/// Estimates the scale of residuals `r` for `estimator`.
///
/// `Ml`: quadratic seed `sigma^2 = mean(r^2)`, then fixed-point iterations of the estimator's
/// likelihood `sigma^2 = mean(w r^2)`, for Student-t alternated with the nu bisection.
/// `MScale`: for Huber/Tukey the Gaussian-consistent M-scale `sigma^2 = mean(w r^2) /
/// E[w Z^2]`, else as `Ml`. `Mad`: 1.4826 MAD (nu then estimated as for `Ml`). `Fixed` is
/// handled by the caller.
pub fn estimate_scale(r: &[f64], estimator: Estimator, method: ScaleMethod) -> ScaleEstimate {
    let n = r.len();
    if n < 8 {
        return ScaleEstimate {
            sigma: 0.0,
            nu: NU_DEFAULT,
        };
    }
    let code = estimator as u32;
    let mut sigma2 = match method {
        ScaleMethod::Mad => mad_sigma(r).powi(2),
        _ => r.iter().map(|x| x * x).sum::<f64>() / n as f64,
    };
    if !(sigma2 > 0.0) {
        return ScaleEstimate {
            sigma: 0.0,
            nu: NU_DEFAULT,
        };
    }
    let mut nu = NU_DEFAULT;
    let mut z2: Vec<f64> = Vec::with_capacity(n);
    match (estimator, method) {
        (Estimator::LeastSquares, _) | (_, ScaleMethod::Mad) | (_, ScaleMethod::Fixed) => {
            if estimator == Estimator::Student {
                z2.extend(r.iter().map(|x| x * x / sigma2));
                nu = estimate_nu(&z2);
            }
        }
        (Estimator::Student, ScaleMethod::Ml | ScaleMethod::MScale) => {
            for outer in 0..2 {
                for _ in 0..8 {
                    let s: f64 = r
                        .iter()
                        .map(|x| x * x * (nu + 1.0) / (nu + x * x / sigma2))
                        .sum();
                    let next = s / n as f64;
                    let done = ((next - sigma2) / sigma2).abs() < SCALE_TOLERANCE;
                    sigma2 = next;
                    if done {
                        break;
                    }
                }
                z2.clear();
                z2.extend(r.iter().map(|x| x * x / sigma2));
                let next_nu = estimate_nu(&z2);
                let done = (next_nu - nu).abs() < 1e-2 && outer > 0;
                nu = next_nu;
                if done {
                    break;
                }
            }
        }
        (Estimator::Huber | Estimator::Tukey, ScaleMethod::Ml | ScaleMethod::MScale) => {
            let c = consistency(code, method);
            for _ in 0..30 {
                let s = sigma2.sqrt();
                let acc: f64 = r
                    .iter()
                    .map(|x| f64::from(weight(code, (x / s) as f32, 0.0)) * x * x)
                    .sum();
                let next = acc / (n as f64 * c);
                let done = ((next - sigma2) / sigma2).abs() < SCALE_TOLERANCE;
                sigma2 = next;
                if done || !(sigma2 > 0.0) {
                    break;
                }
            }
        }
    }
    ScaleEstimate {
        sigma: sigma2.max(0.0).sqrt(),
        nu,
    }
}

/// Like [`estimate_scale`], warm-started from the previous iteration's estimate: the scale
/// takes one fixed-point step from `prev.sigma` and the degrees of freedom are kept. This is
/// the per-iteration update inside a pyramid level (so the fixed-point iteration of the scale
/// continues across Gauss-Newton iterations); the full estimate runs once per level.
pub fn update_scale(
    r: &[f64],
    estimator: Estimator,
    method: ScaleMethod,
    prev: ScaleEstimate,
) -> ScaleEstimate {
    let n = r.len();
    if n < 8 || !(prev.sigma > 0.0) {
        return estimate_scale(r, estimator, method);
    }
    let nu = prev.nu;
    let code = estimator as u32;
    let sigma2 = match (estimator, method) {
        (_, ScaleMethod::Mad) => mad_sigma(r).powi(2),
        (Estimator::LeastSquares, _) | (_, ScaleMethod::Fixed) => {
            r.iter().map(|x| x * x).sum::<f64>() / n as f64
        }
        (Estimator::Student, ScaleMethod::Ml | ScaleMethod::MScale) => {
            let s2 = prev.sigma * prev.sigma;
            r.iter()
                .map(|x| x * x * (nu + 1.0) / (nu + x * x / s2))
                .sum::<f64>()
                / n as f64
        }
        (Estimator::Huber | Estimator::Tukey, ScaleMethod::Ml | ScaleMethod::MScale) => {
            let c = consistency(code, method);
            let s = prev.sigma;
            r.iter()
                .map(|x| f64::from(weight(code, (x / s) as f32, 0.0)) * x * x)
                .sum::<f64>()
                / (n as f64 * c)
        }
    };
    ScaleEstimate {
        sigma: sigma2.max(0.0).sqrt(),
        nu,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn gaussian(n: usize, sigma: f64, seed: u64) -> Vec<f64> {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
        (0..n)
            .map(|_| {
                let u1: f64 = rng.random::<f64>().max(1e-300);
                let u2: f64 = rng.random();
                sigma * (-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()
            })
            .collect()
    }

    #[test]
    fn nu_root_matches_a_fine_scan() {
        // Student-t-like data: Gaussian over a random scale mixture gives nu well inside [2, 10].
        let g = gaussian(6000, 1.0, 7);
        let mix = gaussian(6000, 1.0, 8);
        let z2: Vec<f64> = g
            .iter()
            .zip(&mix)
            .map(|(a, b)| {
                let s = 1.0 + 0.6 * b * b;
                a * a * s
            })
            .collect();
        let nu = estimate_nu(&z2);
        assert!(nu > NU_MIN && nu < NU_MAX, "nu {nu}");
        // The same sub-sample as `estimate_nu`; the derivative changes sign within 2e-3.
        let step = z2.len() as f64 / NU_MAX_SAMPLES as f64;
        let sub: Vec<f64> = (0..NU_MAX_SAMPLES)
            .map(|k| z2[(k as f64 * step) as usize])
            .collect();
        assert!(dlogl_dnu(&sub, nu - 2e-3) > 0.0 && dlogl_dnu(&sub, nu + 2e-3) < 0.0);
    }

    #[test]
    fn digamma_known_values() {
        assert!((digamma(1.0) + 0.5772156649015329).abs() < 1e-10);
        assert!((digamma(0.5) + 1.9635100260214235).abs() < 1e-10);
    }

    #[test]
    fn scales_are_consistent_at_the_gaussian() {
        let r = gaussian(20000, 3.0, 1);
        for est in [Estimator::LeastSquares, Estimator::Huber, Estimator::Tukey] {
            let s = estimate_scale(&r, est, ScaleMethod::MScale).sigma;
            assert!((s - 3.0).abs() < 0.1, "{est:?}: {s}");
        }
        assert!((mad_sigma(&r) - 3.0).abs() < 0.1);
    }

    /// The ML scale of Huber's density `exp(-rho(r/sigma)) / sigma` maximises the likelihood
    /// (Huber's rho is `u^2/2` inside k and `k|u| - k^2/2` outside); Tukey's satisfies the
    /// same stationarity condition; both lie below the Gaussian-consistent M-scale on
    /// Gaussian residuals, where `E[w Z^2] < 1`.
    #[test]
    fn ml_scale_is_the_likelihood_stationary_point() {
        let r = gaussian(20000, 3.0, 3);
        let k = f64::from(HUBER_K);
        let huber_rho = |u: f64| {
            if u.abs() <= k {
                0.5 * u * u
            } else {
                k * u.abs() - 0.5 * k * k
            }
        };
        let log_l = |s: f64| -> f64 { r.iter().map(|x| -s.ln() - huber_rho(x / s)).sum() };
        let ml = estimate_scale(&r, Estimator::Huber, ScaleMethod::Ml).sigma;
        assert!(
            log_l(ml) > log_l(ml * 1.02) && log_l(ml) > log_l(ml * 0.98),
            "huber ml {ml}"
        );
        for est in [Estimator::Huber, Estimator::Tukey] {
            let ml = estimate_scale(&r, est, ScaleMethod::Ml).sigma;
            let m = estimate_scale(&r, est, ScaleMethod::MScale).sigma;
            let code = est as u32;
            let stationary = r
                .iter()
                .map(|x| f64::from(weight(code, (x / ml) as f32, 0.0)) * (x / ml).powi(2))
                .sum::<f64>()
                / r.len() as f64;
            assert!((stationary - 1.0).abs() < 5e-3, "{est:?}: {stationary}");
            assert!(ml < m - 0.05, "{est:?}: ml {ml}, m-scale {m}");
        }
    }

    #[test]
    fn student_scale_ignores_outliers_and_finds_heavy_tails() {
        let mut r = gaussian(20000, 2.0, 2);
        let clean_nu = estimate_scale(&r, Estimator::Student, ScaleMethod::Ml).nu;
        for (i, x) in r.iter_mut().enumerate() {
            if i % 5 == 0 {
                *x = 80.0 * if i % 2 == 0 { 1.0 } else { -1.0 };
            }
        }
        let e = estimate_scale(&r, Estimator::Student, ScaleMethod::Ml);
        let ls = estimate_scale(&r, Estimator::LeastSquares, ScaleMethod::Ml).sigma;
        assert!(ls > 30.0, "{ls}");
        assert!(e.sigma < 4.0, "student sigma {}", e.sigma);
        assert!(
            e.nu < clean_nu && e.nu <= 3.0,
            "nu {} (clean {clean_nu})",
            e.nu
        );
    }
}
