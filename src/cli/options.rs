//! Option groups shared by several commands: the configuration file and `--set` assignments,
//! the odometry flags, the compute backend.

use std::path::{Path, PathBuf};

use anyhow::Context;
use anyhow::Result;
use rgbid::gpu::{BackendChoice, ComputeBackend};
use rgbid::io::config::DROID_PREFIX;
use rgbid::io::settings::{self, Assignment, Provenance};
use rgbid::io::{CalibFormat, OpenOptions};
use rgbid::odometry::{Estimator, GeometricParam, OdometryConfig, ScaleMethod, Terms};
use serde::de::DeserializeOwned;
use serde::Serialize;

/// `--config FILE` and `--set KEY.PATH=VALUE`: the command's configuration as data.
///
/// Precedence, lowest first: the defaults, `--config`, the command's own flags, `--set`.
#[derive(clap::Args, Clone, Debug, Default)]
pub struct ConfigArgs {
    /// Configuration file, TOML or JSON (by the extension). Any subset of the keys: missing
    /// ones keep their defaults, an unknown key is an error. `rgbid config dump --command
    /// NAME` prints every key with its default. Precedence, lowest first: defaults, --config,
    /// the command's flags, --set.
    #[arg(long, value_name = "FILE")]
    pub config: Option<PathBuf>,
    /// Set one configuration value over the file and the flags, e.g. `--set
    /// odometry.estimator=huber` (slam, demo) or `--set estimator=huber` (odometry). The
    /// value is read as TOML (`3`, `0.5`, `true`, `[6, 8, 10]`), anything else as a string;
    /// `null` clears an optional value. Repeatable.
    #[arg(long = "set", value_name = "KEY.PATH=VALUE")]
    pub set: Vec<Assignment>,
}

impl ConfigArgs {
    /// `base`, then the file of `--config`, then `flags` (the command's explicit flags), then
    /// the `--set` assignments.
    pub fn resolve<T: Serialize + DeserializeOwned>(
        &self,
        base: T,
        flags: impl FnOnce(&mut T) -> Result<()>,
    ) -> Result<T> {
        let mut config = match &self.config {
            Some(p) => settings::load_file(&base, p)?,
            None => base,
        };
        flags(&mut config)?;
        if !self.set.is_empty() {
            config = settings::apply_assignments(&config, &self.set)?;
        }
        Ok(config)
    }
}

/// Sets the camera of `opts` from `--camera` read as `--calib-format` says: a preset or camera
/// file (`auto`), or a DROID-SLAM `calib.txt` sized by the sequence's first frame (`droid`).
pub fn set_camera(opts: &mut OpenOptions, camera: Option<&str>, format: CalibFormat) -> Result<()> {
    match (camera, format) {
        (Some(c), CalibFormat::Auto) => {
            opts.camera = Some(c.parse().with_context(|| format!("camera '{c}'"))?);
        }
        (Some(c), CalibFormat::Droid) => opts.droid_calib = Some(PathBuf::from(c)),
        (None, _) => {}
    }
    Ok(())
}

/// `--camera` as [`rgbid::source::SourceSpec`]'s camera text (`droid:FILE` for a DROID-SLAM
/// `calib.txt`).
pub fn camera_spec(camera: Option<&str>, format: CalibFormat) -> Option<String> {
    camera.map(|c| match format {
        CalibFormat::Auto => c.to_string(),
        CalibFormat::Droid => format!("{DROID_PREFIX}{c}"),
    })
}

/// The odometry flags shared by every command that runs the odometry (`odometry`, `slam`,
/// `demo`, `bench odometry`). Each one given overrides the configuration file.
#[derive(clap::Args, Clone, Debug, Default)]
pub struct OdometryOptions {
    /// Robust estimator [default: student].
    #[arg(long, value_enum)]
    pub estimator: Option<Estimator>,
    /// Scale estimation: ml (maximum likelihood), mad, or fixed (sigmaFix) [default: ml].
    #[arg(long, value_enum)]
    pub scale: Option<ScaleMethod>,
    /// Residual terms [default: both].
    #[arg(long, value_enum)]
    pub terms: Option<Terms>,
    /// Geometric error parametrisation [default: inverse-depth].
    #[arg(long, value_enum)]
    pub geometric: Option<GeometricParam>,
    /// Pyramid levels, 1 to 8 [default: 4].
    #[arg(long, value_parser = range::pyramid_levels)]
    pub levels: Option<usize>,
    /// Finest pyramid level used, 0 to 7 and below --levels (0 = full resolution)
    /// [default: 0].
    #[arg(long, value_parser = range::pyramid_level)]
    pub stop_level: Option<usize>,
    /// Levels wider than this many pixels are not optimised (at 640x480 the finest optimised
    /// level is then 320x240); 0 optimises every level down to --stop-level; a whole number >= 0 [default: 320].
    #[arg(long, value_parser = range::count)]
    pub max_width: Option<usize>,
    /// Align every frame to the previous one (no reference-frame keeping).
    #[arg(long)]
    pub frame_to_frame: bool,
    /// Covisibility ratio in [0, 1] below which the reference frame is switched
    /// [default: 0.9].
    #[arg(long, value_parser = range::unit)]
    pub covisibility: Option<f64>,
}

impl OdometryOptions {
    /// Puts the flags that were given onto `c`.
    pub fn apply(&self, c: &mut OdometryConfig) {
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
    }

    /// The odometry configuration of `rgbid odometry` and `rgbid bench odometry`: defaults,
    /// the `--config` file (an `OdometryConfig`, e.g. today's JSON files), these flags,
    /// `--set`; validated.
    pub fn config(&self, files: &ConfigArgs) -> Result<OdometryConfig> {
        let c = files.resolve(OdometryConfig::default(), |c| {
            self.apply(c);
            Ok(())
        })?;
        c.validate()?;
        Ok(c)
    }
}

/// `--backend` and `--adapter`.
#[derive(clap::Args, Clone, Debug, Default)]
pub struct BackendArgs {
    /// Compute backend: auto (a hardware GPU, else the CPU), gpu (any adapter, lavapipe
    /// included), cpu (rayon).
    #[arg(long, value_enum, default_value_t = BackendChoice::Auto)]
    pub backend: BackendChoice,
    /// Use the GPU adapter whose name contains this (case-insensitive).
    #[arg(long)]
    pub adapter: Option<String>,
}

/// Writes the provenance of `output` (the configuration, version, commit, backend and
/// command line) to its sidecar `<output>.json` and says so in the log.
pub fn write_sidecar<T: Serialize>(
    output: &Path,
    config: &T,
    backend: &ComputeBackend,
) -> Result<()> {
    let path = Provenance::new(config, backend)?.write_sidecar(output)?;
    log::info!("provenance in {}", path.display());
    Ok(())
}

/// Value parsers that check a number's range at parse time, so a bad value is a usage error
/// (exit code 2) naming the option and its valid range, before any work starts. clap adds
/// "invalid value 'X' for '--option <VALUE>'" in front of the message returned here.
pub mod range {
    /// A number that `ok` accepts; `valid` says which ("must be a finite number > 0").
    fn real(s: &str, valid: &str, ok: impl Fn(f64) -> bool) -> Result<f64, String> {
        match s.trim().parse::<f64>() {
            Ok(v) if ok(v) => Ok(v),
            Ok(_) => Err(valid.to_string()),
            Err(_) => Err(format!("not a number: {valid}")),
        }
    }

    /// A walker's height: metres in (0, 3].
    pub fn walker_height(s: &str) -> Result<f64, String> {
        real(s, "must be a height in metres in (0, 3]", |v| {
            v.is_finite() && v > 0.0 && v <= 3.0
        })
    }

    /// A finite number > 0.
    pub fn positive(s: &str) -> Result<f64, String> {
        real(s, "must be a finite number > 0", |v| {
            v.is_finite() && v > 0.0
        })
    }

    /// A finite number >= 0.
    pub fn non_negative(s: &str) -> Result<f64, String> {
        real(s, "must be a finite number >= 0", |v| {
            v.is_finite() && v >= 0.0
        })
    }

    /// A number > 0, `inf` included (a limit that `inf` switches off).
    pub fn positive_or_inf(s: &str) -> Result<f64, String> {
        real(
            s,
            "must be a number > 0 (inf switches the limit off)",
            |v| v > 0.0,
        )
    }

    /// A number in [0, 1].
    pub fn unit(s: &str) -> Result<f64, String> {
        real(s, "must be a number in [0, 1]", |v| {
            (0.0..=1.0).contains(&v)
        })
    }

    /// A number in (0, 1).
    pub fn open_unit(s: &str) -> Result<f64, String> {
        real(s, "must be a number in (0, 1)", |v| v > 0.0 && v < 1.0)
    }

    /// A frame rate for `--realtime`: finite, in [0.001, 10000] frames per second (the
    /// upper end is far beyond any camera; the lower end keeps the waits representable).
    pub fn frame_rate(s: &str) -> Result<f64, String> {
        real(
            s,
            "must be a frame rate in [0.001, 10000] frames per second",
            |v| (1e-3..=1e4).contains(&v),
        )
    }

    fn integer(s: &str, lo: usize, hi: usize) -> Result<usize, String> {
        let valid = if hi == usize::MAX {
            format!("a whole number >= {lo}")
        } else {
            format!("a whole number in {lo} to {hi}")
        };
        let v: usize = s.trim().parse().map_err(|_| format!("not {valid}"))?;
        if (lo..=hi).contains(&v) {
            Ok(v)
        } else {
            Err(format!("must be {valid}"))
        }
    }

    /// An integer in `[lo, hi]` of a narrower type.
    fn integer_as<T: TryFrom<usize>>(s: &str, lo: usize, hi: usize) -> Result<T, String> {
        T::try_from(integer(s, lo, hi)?).map_err(|_| format!("must be at most {hi}"))
    }

    /// Any finite number (negative included).
    pub fn finite(s: &str) -> Result<f64, String> {
        real(s, "must be a finite number", |v| v.is_finite())
    }

    /// A finite number >= 1.
    pub fn at_least_one_real(s: &str) -> Result<f64, String> {
        real(s, "must be a finite number >= 1", |v| {
            v.is_finite() && v >= 1.0
        })
    }

    /// A finite number > 0, as f32.
    pub fn positive_f32(s: &str) -> Result<f32, String> {
        let valid = "must be a finite number > 0 (single precision)";
        real(s, valid, |v| (v as f32).is_finite() && v as f32 > 0.0).map(|v| v as f32)
    }

    /// A finite number, as f32.
    pub fn finite_f32(s: &str) -> Result<f32, String> {
        let valid = "must be a finite number (single precision)";
        real(s, valid, |v| (v as f32).is_finite()).map(|v| v as f32)
    }

    /// A number in (-1, 1) (a correlation threshold).
    pub fn open_signed_unit(s: &str) -> Result<f64, String> {
        real(s, "must be a number in (-1, 1)", |v| v > -1.0 && v < 1.0)
    }

    /// A whole number >= 0.
    pub fn count(s: &str) -> Result<usize, String> {
        integer(s, 0, usize::MAX)
    }

    /// A whole number >= 10 (particles of a filter).
    pub fn at_least_ten(s: &str) -> Result<usize, String> {
        integer(s, 10, usize::MAX)
    }

    /// An image side in pixels: 16 to 16384.
    pub fn image_side(s: &str) -> Result<u32, String> {
        integer_as(s, 16, 16384)
    }

    /// A seed: any whole number in 0 to 2^64 - 1.
    pub fn seed(s: &str) -> Result<u64, String> {
        s.trim()
            .parse()
            .map_err(|_| "not a whole number in 0 to 18446744073709551615".into())
    }

    /// A number of seeds: 1 to 1000.
    pub fn seeds(s: &str) -> Result<u64, String> {
        integer_as(s, 1, 1000)
    }

    /// A session of a generated scene: 0 (as generated) to 1000.
    pub fn session(s: &str) -> Result<u32, String> {
        integer_as(s, 0, 1000)
    }

    /// A number of sessions: 1 to 1000.
    pub fn sessions(s: &str) -> Result<u32, String> {
        integer_as(s, 1, 1000)
    }

    /// A pixel step (finite differences): 1 to 64.
    pub fn pixel_step(s: &str) -> Result<u32, String> {
        integer_as(s, 1, 64)
    }

    /// A radius in pixels: 0 to 64.
    pub fn pixel_radius(s: &str) -> Result<u32, String> {
        integer_as(s, 0, 64)
    }

    /// Sub-frames of a motion-blurred render: 0 (off) to 64.
    pub fn sub_frames(s: &str) -> Result<usize, String> {
        integer(s, 0, 64)
    }

    /// A whole number >= 1.
    pub fn at_least_one(s: &str) -> Result<usize, String> {
        integer(s, 1, usize::MAX)
    }

    /// A whole number >= 2.
    pub fn at_least_two(s: &str) -> Result<usize, String> {
        integer(s, 2, usize::MAX)
    }

    /// A whole number >= 8 (an 8-point essential-matrix sample).
    pub fn at_least_eight(s: &str) -> Result<usize, String> {
        integer(s, 8, usize::MAX)
    }

    /// Pyramid levels: 1 to 8.
    pub fn pyramid_levels(s: &str) -> Result<usize, String> {
        integer(s, 1, 8)
    }

    /// A pyramid level index: 0 to 7.
    pub fn pyramid_level(s: &str) -> Result<usize, String> {
        integer(s, 0, 7)
    }

    #[cfg(test)]
    mod tests {
        use super::*;

        #[test]
        fn ranges_reject_nan_inf_zero_and_negative() {
            for bad in ["0", "1e-300", "nan", "NaN", "-1", "inf", "-inf", "x", ""] {
                assert!(frame_rate(bad).is_err(), "{bad}");
            }
            for bad in ["0", "nan", "NaN", "-1", "inf", "-inf", "x", ""] {
                assert!(positive(bad).is_err(), "{bad}");
            }
            assert_eq!(positive("1e-300"), Ok(1e-300));
            assert_eq!(frame_rate("30"), Ok(30.0));
            assert_eq!(positive_or_inf("inf"), Ok(f64::INFINITY));
            assert!(positive_or_inf("nan").is_err());
            assert!(positive_or_inf("0").is_err());
            assert!(unit("1.5").is_err() && unit("nan").is_err());
            assert_eq!(unit("0.7"), Ok(0.7));
            assert!(open_unit("1").is_err() && open_unit("0").is_err());
            assert_eq!(non_negative("0"), Ok(0.0));
            assert!(non_negative("-0.1").is_err() && non_negative("inf").is_err());
            assert_eq!(pyramid_levels("8"), Ok(8));
            assert!(pyramid_levels("9").unwrap_err().contains("1 to 8"));
            assert!(pyramid_levels("0").is_err());
            assert!(at_least_one("0").unwrap_err().contains(">= 1"));
            assert!(at_least_one("-3").unwrap_err().contains("whole number"));
            assert_eq!(image_side("16"), Ok(16));
            assert!(image_side("15").unwrap_err().contains("16 to 16384"));
            assert!(image_side("99999999999")
                .unwrap_err()
                .contains("16 to 16384"));
            assert_eq!(session("0"), Ok(0));
            assert!(sessions("0").is_err() && pixel_step("0").is_err());
            assert_eq!(finite("-2.5"), Ok(-2.5));
            assert!(finite("inf").is_err() && finite("nan").is_err());
            assert!(open_signed_unit("-1").is_err() && open_signed_unit("1").is_err());
            assert_eq!(open_signed_unit("-0.5"), Ok(-0.5));
            assert!(positive_f32("1e39").is_err() && positive_f32("0").is_err());
            assert!(finite_f32("1e39").is_err());
            assert!(seed("-1").is_err() && seed("18446744073709551615").is_ok());
            assert!(at_least_one_real("0.5").is_err() && at_least_one_real("1").is_ok());
            assert!(at_least_ten("9").unwrap_err().contains(">= 10"));
            assert_eq!(count("0"), Ok(0));
        }
    }
}
