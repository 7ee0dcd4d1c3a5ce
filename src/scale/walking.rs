//! Walking speed from step frequency, `V = alpha f^beta H` (thesis eq. 3.11), and the
//! calibration of `alpha`, `beta` from walks of known length (3.4.1).

use serde::{Deserialize, Serialize};

use super::{check_param, ScaleError};

/// Grieve's `alpha` (speed per height at one step per second).
pub const GRIEVE_ALPHA: f64 = 0.2896;
/// Grieve's `beta` (exponent of the step frequency).
pub const GRIEVE_BETA: f64 = 1.7544;

/// The walking model of one person: `V = alpha f^beta H`, `V` m/s, `f` steps/s, `H` metres.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct WalkingModel {
    /// Height of the walker, metres.
    pub height: f64,
    /// `alpha` (unitless: `V / H` at `f = 1` step/s, in 1/s).
    pub alpha: f64,
    /// `beta`, exponent of the step frequency.
    pub beta: f64,
}

impl Default for WalkingModel {
    /// Grieve's model for a walker of 1.70 m.
    fn default() -> Self {
        WalkingModel::grieve(1.7)
    }
}

impl WalkingModel {
    /// A model with Grieve's `alpha` and `beta` for a walker of `height` metres.
    pub fn grieve(height: f64) -> WalkingModel {
        WalkingModel {
            height,
            alpha: GRIEVE_ALPHA,
            beta: GRIEVE_BETA,
        }
    }
    /// Checks that height, alpha and beta are positive and finite.
    pub fn validate(&self) -> Result<(), ScaleError> {
        for (name, v) in [
            ("height", self.height),
            ("alpha", self.alpha),
            ("beta", self.beta),
        ] {
            check_param(name, v.is_finite() && v > 0.0, || {
                format!("{v} must be > 0")
            })?;
        }
        Ok(())
    }
    /// Walking speed in m/s at step frequency `f` steps/s (0 for `f <= 0`).
    pub fn speed(&self, f: f64) -> f64 {
        if f > 0.0 {
            self.alpha * f.powf(self.beta) * self.height
        } else {
            0.0
        }
    }
    /// Step frequency in steps/s of a walk at `speed` m/s (the inverse of [`Self::speed`];
    /// 0 for `speed <= 0`).
    pub fn frequency(&self, speed: f64) -> f64 {
        if speed > 0.0 {
            (speed / (self.alpha * self.height)).powf(1.0 / self.beta)
        } else {
            0.0
        }
    }
}

/// One calibration walk: a straight walk of known length at a steady pace.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct CalibrationSample {
    /// Mean step period, seconds per step.
    pub step_period: f64,
    /// Distance walked, metres.
    pub distance: f64,
    /// Time taken, seconds.
    pub time: f64,
}

/// Fits `alpha`, `beta` of `V = alpha f^beta H` to calibration walks by a power fit (linear
/// least squares of `ln(V / H) = ln alpha + beta ln f`, `f = 1 / step_period`,
/// `V = distance / time`). Needs two walks at different paces at least.
pub fn calibrate(height: f64, samples: &[CalibrationSample]) -> Result<WalkingModel, ScaleError> {
    check_param("height", height.is_finite() && height > 0.0, || {
        format!("{height} m must be > 0")
    })?;
    if samples.len() < 2 {
        return Err(ScaleError::Calibration(format!(
            "need at least 2 walks at different paces, got {}",
            samples.len()
        )));
    }
    let mut xs = Vec::with_capacity(samples.len());
    let mut ys = Vec::with_capacity(samples.len());
    for (i, s) in samples.iter().enumerate() {
        let ok = [s.step_period, s.distance, s.time]
            .iter()
            .all(|v| v.is_finite() && *v > 0.0);
        if !ok {
            return Err(ScaleError::Calibration(format!(
                "walk {}: step period, distance and time must be finite and > 0 ({:?})",
                i + 1,
                s
            )));
        }
        xs.push((1.0 / s.step_period).ln());
        ys.push((s.distance / s.time / height).ln());
    }
    let n = xs.len() as f64;
    let mx = xs.iter().sum::<f64>() / n;
    let my = ys.iter().sum::<f64>() / n;
    let sxx: f64 = xs.iter().map(|x| (x - mx).powi(2)).sum();
    let sxy: f64 = xs.iter().zip(&ys).map(|(x, y)| (x - mx) * (y - my)).sum();
    if sxx < 1e-10 {
        return Err(ScaleError::Calibration(
            "all walks have the same step period: beta is undetermined".into(),
        ));
    }
    let beta = sxy / sxx;
    let alpha = (my - beta * mx).exp();
    let m = WalkingModel {
        height,
        alpha,
        beta,
    };
    m.validate()
        .map_err(|e| ScaleError::Calibration(format!("fit gave {e}")))?;
    Ok(m)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn calibration_recovers_model() {
        let truth = WalkingModel {
            height: 1.7,
            alpha: 0.31,
            beta: 1.6,
        };
        let samples: Vec<CalibrationSample> = [1.2, 1.5, 1.8, 2.1, 2.4]
            .iter()
            .map(|&f| CalibrationSample {
                step_period: 1.0 / f,
                distance: 30.0,
                time: 30.0 / truth.speed(f),
            })
            .collect();
        let m = calibrate(1.7, &samples).unwrap();
        assert!(
            (m.alpha - 0.31).abs() < 1e-9 && (m.beta - 1.6).abs() < 1e-9,
            "{m:?}"
        );
        assert!(calibrate(1.7, &samples[..1]).is_err());
        let same = vec![samples[0]; 3];
        assert!(matches!(
            calibrate(1.7, &same),
            Err(ScaleError::Calibration(_))
        ));
    }
}
