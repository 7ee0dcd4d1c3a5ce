//! Camera configuration: built-in presets, `key = value` config files and TUM-style
//! `calib.txt` files.
//!
//! A config file holds one `key = value` (or `key: value`) pair per line; `#` starts a comment.
//! Keys: `fx fy cx cy` (pixels, pixel centres at integers), `width height` (pixels, default
//! 640 x 480), `depth_factor` (raw depth units per metre, default 5000), `k1 k2 p1 p2 k3`
//! (Brown-Conrady distortion of the raw images, default 0), and optionally `preset = NAME` to
//! start from a preset and override some of its values. Errors name `file:line`.
//!
//! `calib.txt` (beside a sequence) is one line `fx fy cx cy [depth_factor [width height]]`.
//!
//! DROID-SLAM's `calib.txt` ([`CalibFormat::Droid`], only when asked for: it shares the
//! name) is one line `fx fy cx cy [k1 k2 p1 p2 [k3]]` without the image size, which comes from
//! the images ([`CameraConfig::parse_droid`]).

use std::path::{Path, PathBuf};
use std::str::FromStr;

use super::IoError;
use crate::camera::{BrownConrady, PinholeCamera};

/// Names of the built-in camera presets.
pub const PRESETS: [&str; 7] = [
    "default", "tum_fr1", "tum_fr2", "tum_fr3", "icl_nuim", "7scenes", "replica",
];

/// How a camera file named on the command line is read.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
pub enum CalibFormat {
    /// By the file: `calib.txt` is rgbid's `fx fy cx cy [depth_factor [width height]]`,
    /// `.yaml` / `.yml` OpenCV / ORB-SLAM, anything else `key = value` lines; or a preset name.
    #[default]
    Auto,
    /// DROID-SLAM's `calib.txt`: one line `fx fy cx cy [k1 k2 p1 p2 [k3]]` (pixels; Brown-Conrady
    /// distortion of the raw images). It holds no image size (taken from the sequence's first
    /// frame) and no depth scale (the layout's).
    Droid,
}

/// TUM's depth factor: raw 16-bit depth units per metre.
pub const TUM_DEPTH_FACTOR: f64 = 5000.0;

/// The constant depth-scale correction `ds` of the Freiburg 2 Kinect (true depth = `ds` times
/// the stored depth), as the TUM RGB-D dataset documents it for its fr2 sequences and as the
/// thesis applies it to them (6.5.1). The `tum_fr2` preset divides the depth factor by it.
pub const TUM_FR2_DEPTH_SCALE: f64 = 1.031;

/// The rolling-shutter readout (seconds, first row to last) of the Kinect v1 colour camera
/// in the presets of data recorded with one (`tum_fr1`, `tum_fr2`, `7scenes`). An effective
/// value, not a data sheet's: the readout whose rectification gives the best mean odometry
/// ATE against OpenCV's over fr1/rpy 0-199 and redkitchen 0-299 in a sweep of 0-40 ms
/// (docs/notes.md), the rule by which the odometry's defaults are chosen.
pub const KINECT_READOUT: f64 = 0.010;

/// A camera with its depth scale and a note of where it came from.
#[derive(Clone, Debug, PartialEq)]
pub struct CameraConfig {
    /// Intrinsics (pixels) and the distortion of the raw images.
    pub camera: PinholeCamera,
    /// Raw depth units per metre (TUM: 5000, millimetre data: 1000).
    pub depth_factor: f64,
    /// Where the values came from (`preset tum_fr1`, a file path...), for logs.
    pub source: String,
}

impl CameraConfig {
    /// A built-in preset. 640 x 480 with depth factor 5000: `tum_fr1`/`tum_fr2` carry the
    /// official TUM RGB-D intrinsics and distortion of the Freiburg 1/2 Kinects, and `tum_fr2`
    /// also the fr2 depth-scale correction ([`TUM_FR2_DEPTH_SCALE`]: depth factor 5000 / 1.031;
    /// a camera file with `preset = tum_fr2` and `depth_factor = 5000` undoes it); `tum_fr3` is
    /// the (already undistorted) Freiburg 3 camera; `default` is the ROS default (525, 525,
    /// 319.5, 239.5) without distortion; `icl_nuim` is ICL-NUIM's TUM-compatible variant
    /// (481.2, 480, 319.5, 239.5). `7scenes`: Microsoft 7-Scenes (585, 585, 320, 240; 640 x
    /// 480, millimetre depth). `replica`: Replica as rendered for NICE-SLAM (600, 600, 599.5,
    /// 339.5; 1200 x 680, depth factor 6553.5). `tum_fr1`, `tum_fr2` and `7scenes` (Kinect v1
    /// recordings) carry the rolling-shutter readout [`KINECT_READOUT`]; the others are
    /// global-shutter cameras (`tum_fr3`'s readout is not measured here; a camera file with
    /// `preset = tum_fr3` and `readout = 0.01` sets one).
    pub fn preset(name: &str) -> Option<CameraConfig> {
        let other = |fx, fy, cx, cy, w, h, depth_factor, readout| {
            let mut camera = PinholeCamera::new(fx, fy, cx, cy, w, h);
            camera.readout = readout;
            Some(CameraConfig {
                camera,
                depth_factor,
                source: format!("preset {name}"),
            })
        };
        let (fx, fy, cx, cy, d, depth_scale, readout) = match name.to_ascii_lowercase().as_str() {
            "icl_nuim" | "icl" => return other(481.2, 480.0, 319.5, 239.5, 640, 480, 5000.0, 0.0),
            "7scenes" | "7-scenes" => {
                return other(585.0, 585.0, 320.0, 240.0, 640, 480, 1000.0, KINECT_READOUT)
            }
            "replica" => return other(600.0, 600.0, 599.5, 339.5, 1200, 680, 6553.5, 0.0),
            "default" => (
                525.0,
                525.0,
                319.5,
                239.5,
                BrownConrady::default(),
                1.0,
                0.0,
            ),
            "tum_fr1" | "fr1" | "freiburg1" => (
                517.3,
                516.5,
                318.6,
                255.3,
                BrownConrady {
                    k1: 0.2624,
                    k2: -0.9531,
                    p1: -0.0054,
                    p2: 0.0026,
                    k3: 1.1633,
                },
                // The dataset's fr1 factor (1.035) makes odometry and SLAM worse on fr1/rpy,
                // and the thesis corrects fr2 alone.
                1.0,
                KINECT_READOUT,
            ),
            "tum_fr2" | "fr2" | "freiburg2" => (
                520.9,
                521.0,
                325.1,
                249.7,
                BrownConrady {
                    k1: 0.2312,
                    k2: -0.7849,
                    p1: -0.0033,
                    p2: -0.0001,
                    k3: 0.9172,
                },
                TUM_FR2_DEPTH_SCALE,
                KINECT_READOUT,
            ),
            "tum_fr3" | "fr3" | "freiburg3" => (
                535.4,
                539.2,
                320.1,
                247.6,
                BrownConrady::default(),
                1.0,
                0.0,
            ),
            _ => return None,
        };
        let mut camera = PinholeCamera::new(fx, fy, cx, cy, 640, 480);
        camera.distortion = d;
        camera.readout = readout;
        Some(CameraConfig {
            camera,
            depth_factor: TUM_DEPTH_FACTOR / depth_scale,
            source: format!("preset {name}"),
        })
    }

    /// Reads a `key = value` camera config file.
    pub fn from_file(path: &Path) -> Result<CameraConfig, IoError> {
        let text = super::read_text(path)?;
        Self::parse_config(&text, path)
    }

    /// Parses the text of a `key = value` camera config; `path` is only used in errors.
    pub fn parse_config(text: &str, path: &Path) -> Result<CameraConfig, IoError> {
        let mut base: Option<CameraConfig> = None;
        let mut values: Vec<(&'static str, f64, usize)> = Vec::new();
        const KEYS: [&str; 13] = [
            "fx",
            "fy",
            "cx",
            "cy",
            "depth_factor",
            "width",
            "height",
            "k1",
            "k2",
            "p1",
            "p2",
            "k3",
            "readout",
        ];
        for (i, raw) in text.lines().enumerate() {
            let line = i + 1;
            let s = raw.split('#').next().unwrap_or("").trim();
            if s.is_empty() {
                continue;
            }
            let Some(pos) = s.find(['=', ':']) else {
                return Err(IoError::parse(
                    path,
                    line,
                    format!("expected `key = value`, found '{s}'"),
                ));
            };
            let key = s[..pos].trim().to_ascii_lowercase();
            let value = s[pos + 1..].trim();
            if key == "preset" {
                if base.is_some() {
                    return Err(IoError::parse(path, line, "preset given twice"));
                }
                base = Some(Self::preset(value).ok_or_else(|| {
                    IoError::parse(
                        path,
                        line,
                        format!("unknown preset '{value}' (known: {})", PRESETS.join(", ")),
                    )
                })?);
                continue;
            }
            let Some(&k) = KEYS.iter().find(|k| **k == key) else {
                return Err(IoError::parse(
                    path,
                    line,
                    format!("unknown key '{key}' (known: preset, {})", KEYS.join(", ")),
                ));
            };
            if values.iter().any(|(n, _, _)| *n == k) {
                return Err(IoError::parse(path, line, format!("key '{k}' given twice")));
            }
            let v: f64 = value.parse().map_err(|_| {
                IoError::parse(
                    path,
                    line,
                    format!("value of '{k}' is not a number: '{value}'"),
                )
            })?;
            if !v.is_finite() {
                return Err(IoError::parse(
                    path,
                    line,
                    format!("value of '{k}' is not finite: '{value}'"),
                ));
            }
            values.push((k, v, line));
        }
        let has = |k: &str| values.iter().any(|(n, _, _)| *n == k);
        if base.is_none() {
            if let Some(missing) = ["fx", "fy", "cx", "cy"].into_iter().find(|k| !has(k)) {
                return Err(IoError::parse(
                    path,
                    text.lines().count().max(1),
                    format!("missing key '{missing}' (fx, fy, cx, cy are required unless a preset is given)"),
                ));
            }
        }
        let mut cfg = base.unwrap_or(CameraConfig {
            camera: PinholeCamera::new(1.0, 1.0, 0.0, 0.0, 640, 480),
            depth_factor: TUM_DEPTH_FACTOR,
            source: String::new(),
        });
        for &(k, v, line) in &values {
            let c = &mut cfg.camera;
            match k {
                "fx" => c.fx = v,
                "fy" => c.fy = v,
                "cx" => c.cx = v,
                "cy" => c.cy = v,
                "depth_factor" => cfg.depth_factor = v,
                "width" | "height" => {
                    if !((1.0..=65535.0).contains(&v) && v.fract() == 0.0) {
                        return Err(IoError::parse(
                            path,
                            line,
                            format!("{k} must be a positive integer, got {v}"),
                        ));
                    }
                    if k == "width" {
                        c.width = v as u32;
                    } else {
                        c.height = v as u32;
                    }
                }
                "k1" => c.distortion.k1 = v,
                "k2" => c.distortion.k2 = v,
                "p1" => c.distortion.p1 = v,
                "p2" => c.distortion.p2 = v,
                "readout" => c.readout = v,
                _ => c.distortion.k3 = v,
            }
        }
        cfg.source = path.display().to_string();
        cfg.validate(path)?;
        Ok(cfg)
    }

    /// Reads a TUM-style `calib.txt`: one line `fx fy cx cy [depth_factor [width height]]`
    /// (defaults 5000, 640 x 480); `#` comments and blank lines are skipped.
    pub fn from_calib_txt(path: &Path) -> Result<CameraConfig, IoError> {
        let text = super::read_text(path)?;
        let mut found = None;
        for (i, raw) in text.lines().enumerate() {
            let s = raw.split('#').next().unwrap_or("").trim();
            if s.is_empty() {
                continue;
            }
            if found.is_some() {
                return Err(IoError::parse(
                    path,
                    i + 1,
                    "calib.txt holds more than one line of numbers",
                ));
            }
            let v = parse_numbers(s).map_err(|m| IoError::parse(path, i + 1, m))?;
            if !matches!(v.len(), 4 | 5 | 7) {
                return Err(IoError::parse(
                    path,
                    i + 1,
                    format!(
                        "expected `fx fy cx cy [depth_factor [width height]]`, found {} numbers",
                        v.len()
                    ),
                ));
            }
            let (w, h) = if v.len() == 7 {
                (v[5], v[6])
            } else {
                (640.0, 480.0)
            };
            let size_ok = |x: f64| (1.0..=65535.0).contains(&x) && x.fract() == 0.0;
            if !(size_ok(w) && size_ok(h)) {
                return Err(IoError::parse(
                    path,
                    i + 1,
                    format!("image size {w} x {h} is not a positive integer size"),
                ));
            }
            let camera = PinholeCamera::new(v[0], v[1], v[2], v[3], w as u32, h as u32);
            let depth_factor = v.get(4).copied().unwrap_or(TUM_DEPTH_FACTOR);
            found = Some(CameraConfig {
                camera,
                depth_factor,
                source: path.display().to_string(),
            });
        }
        let cfg = found.ok_or_else(|| IoError::Empty {
            path: path.into(),
            message: "no calibration line".into(),
        })?;
        cfg.validate(path)?;
        Ok(cfg)
    }

    /// Reads DROID-SLAM's `calib.txt` ([`CalibFormat::Droid`]) for images of `width` x
    /// `height` pixels with `depth_factor` raw depth units per metre.
    pub fn from_droid_calib(
        path: &Path,
        width: u32,
        height: u32,
        depth_factor: f64,
    ) -> Result<CameraConfig, IoError> {
        let text = super::read_text(path)?;
        Self::parse_droid(&text, path, width, height, depth_factor)
    }

    /// Parses the text of a DROID-SLAM `calib.txt`: one line `fx fy cx cy [k1 k2 p1 p2 [k3]]`
    /// (pixels, pixel centres at integers; numbers separated by spaces or commas), `#`
    /// comments and blank lines skipped. The file holds no image size or depth scale: they
    /// are `width` x `height` pixels and `depth_factor` units per metre. Errors name
    /// `path:line` and the cause; `path` is only used in errors.
    pub fn parse_droid(
        text: &str,
        path: &Path,
        width: u32,
        height: u32,
        depth_factor: f64,
    ) -> Result<CameraConfig, IoError> {
        let mut lines = text
            .lines()
            .enumerate()
            .map(|(i, l)| (i + 1, l.split('#').next().unwrap_or("").trim()))
            .filter(|(_, l)| !l.is_empty());
        let (line, s) = lines.next().ok_or_else(|| IoError::Empty {
            path: path.into(),
            message: "no calibration line (DROID-SLAM calib.txt: `fx fy cx cy [k1 k2 p1 p2 [k3]]`)"
                .into(),
        })?;
        if let Some((extra, _)) = lines.next() {
            return Err(IoError::parse(
                path,
                extra,
                "a DROID-SLAM calib.txt holds one line of numbers",
            ));
        }
        let v = parse_numbers(s).map_err(|m| IoError::parse(path, line, m))?;
        if !matches!(v.len(), 4 | 8 | 9) {
            return Err(IoError::parse(
                path,
                line,
                format!(
                    "expected `fx fy cx cy [k1 k2 p1 p2 [k3]]` (4, 8 or 9 numbers), found {}",
                    v.len()
                ),
            ));
        }
        let mut camera = PinholeCamera::new(v[0], v[1], v[2], v[3], width, height);
        if v.len() > 4 {
            camera.distortion = BrownConrady {
                k1: v[4],
                k2: v[5],
                p1: v[6],
                p2: v[7],
                k3: v.get(8).copied().unwrap_or(0.0),
            };
        }
        let cfg = CameraConfig {
            camera,
            depth_factor,
            source: format!("{} (DROID-SLAM calib)", path.display()),
        };
        cfg.validate(path)?;
        Ok(cfg)
    }

    /// A preset name or, failing that, the path of a camera file (for a `--camera` flag):
    /// `calib.txt`, OpenCV / ORB-SLAM YAML (`.yaml`, `.yml`), else `key = value` lines.
    pub fn from_name_or_path(s: &str) -> Result<CameraConfig, IoError> {
        if let Some(c) = Self::preset(s) {
            return Ok(c);
        }
        let p = PathBuf::from(s);
        if p.is_file() {
            if p.file_name().is_some_and(|n| n == "calib.txt") {
                return Self::from_calib_txt(&p);
            }
            let ext = p
                .extension()
                .and_then(|e| e.to_str())
                .map(str::to_ascii_lowercase);
            if matches!(ext.as_deref(), Some("yaml" | "yml")) {
                return Self::from_opencv_yaml(&p);
            }
            return Self::from_file(&p);
        }
        if let Some(file) = s.strip_prefix(DROID_PREFIX) {
            return Err(IoError::Malformed {
                path: file.into(),
                message: "a DROID-SLAM calibration holds no image size: it is read with a \
                          sequence folder, whose first frame gives the size"
                    .into(),
            });
        }
        Err(IoError::UnknownCamera {
            name: s.to_string(),
            presets: PRESETS.join(", "),
        })
    }

    /// Checks intrinsics and depth factor; errors name `path`.
    pub fn validate(&self, path: &Path) -> Result<(), IoError> {
        self.camera
            .validate()
            .map_err(|source| IoError::InvalidCamera {
                path: path.into(),
                source,
            })?;
        if !(self.depth_factor.is_finite() && self.depth_factor > 0.0) {
            return Err(IoError::InvalidDepthFactor {
                path: path.into(),
                factor: self.depth_factor,
            });
        }
        Ok(())
    }
}

impl FromStr for CameraConfig {
    type Err = IoError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Self::from_name_or_path(s)
    }
}

/// The prefix of a camera given as text (`SourceSpec`'s `camera`) that names a DROID-SLAM
/// `calib.txt` ([`CalibFormat::Droid`]): `droid:FILE`.
pub const DROID_PREFIX: &str = "droid:";

/// Splits on whitespace and commas and parses finite f64s; the message names the bad field.
pub(crate) fn parse_numbers(s: &str) -> Result<Vec<f64>, String> {
    s.split(|c: char| c.is_whitespace() || c == ',')
        .filter(|t| !t.is_empty())
        .enumerate()
        .map(|(k, t)| match t.parse::<f64>() {
            Ok(v) if v.is_finite() => Ok(v),
            Ok(_) => Err(format!("field {} is not finite ({t})", k + 1)),
            Err(_) => Err(format!("field {} '{t}' is not a number", k + 1)),
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn presets_exist_and_validate() {
        for p in PRESETS {
            let c = CameraConfig::preset(p).unwrap();
            c.validate(Path::new(p)).unwrap();
            let want = match p {
                "7scenes" => 1000.0,
                "replica" => 6553.5,
                "tum_fr2" => 5000.0 / 1.031,
                _ => 5000.0,
            };
            assert_eq!(c.depth_factor, want, "{p}");
        }
        assert!(
            CameraConfig::preset("tum_fr1")
                .unwrap()
                .camera
                .distortion
                .k1
                > 0.26
        );
        assert!(CameraConfig::preset("tum_fr3")
            .unwrap()
            .camera
            .distortion
            .is_zero());
        assert!(CameraConfig::preset("nope").is_none());
    }

    #[test]
    fn droid_calib_parses_and_reports_lines() {
        let p = Path::new("calib.txt");
        let c =
            CameraConfig::parse_droid("# DROID\n500 501 300 200\n", p, 320, 240, 1000.0).unwrap();
        assert_eq!(
            (c.camera.fx, c.camera.fy, c.camera.cx, c.camera.cy),
            (500.0, 501.0, 300.0, 200.0)
        );
        assert_eq!(
            (c.camera.width, c.camera.height, c.depth_factor),
            (320, 240, 1000.0)
        );
        assert!(c.camera.distortion.is_zero());
        let c =
            CameraConfig::parse_droid("500 500 300 200 0.1 -0.2 0.01 0.02", p, 640, 480, 5000.0)
                .unwrap();
        let d = c.camera.distortion;
        assert_eq!((d.k1, d.k2, d.p1, d.p2, d.k3), (0.1, -0.2, 0.01, 0.02, 0.0));
        let c = CameraConfig::parse_droid(
            "500,500,300,200,0.1,-0.2,0.01,0.02,0.3",
            p,
            640,
            480,
            5000.0,
        )
        .unwrap();
        assert_eq!(c.camera.distortion.k3, 0.3);
        let err = |text: &str| {
            CameraConfig::parse_droid(text, p, 640, 480, 5000.0)
                .unwrap_err()
                .to_string()
        };
        let e = err("\n500 500 300\n");
        assert!(
            e.starts_with("calib.txt:2:") && e.contains("found 3"),
            "{e}"
        );
        let e = err("500 500 300 200 0.1\n");
        assert!(e.contains(":1:") && e.contains("found 5"), "{e}");
        let e = err("500 500 x 200\n");
        assert!(
            e.contains(":1:") && e.contains("'x' is not a number"),
            "{e}"
        );
        let e = err("500 500 300 200\n1 2 3 4\n");
        assert!(e.contains(":2:") && e.contains("one line"), "{e}");
        let e = err("# nothing\n");
        assert!(
            e.contains("calib.txt") && e.contains("no calibration line"),
            "{e}"
        );
        let e = err("-500 500 300 200\n");
        assert!(e.contains("calib.txt"), "{e}");
        assert!(CameraConfig::from_name_or_path("droid:calib.txt")
            .unwrap_err()
            .to_string()
            .contains("no image size"));
    }

    #[test]
    fn config_text_parses_and_reports_lines() {
        let p = Path::new("cam.cfg");
        let c = CameraConfig::parse_config(
            "# c\nfx = 500\nfy: 501\ncx=300 # x\ncy = 200\nk1 = 0.1\nwidth = 320\nheight = 240\n",
            p,
        )
        .unwrap();
        assert_eq!(
            (c.camera.fx, c.camera.fy, c.camera.cx, c.camera.cy),
            (500.0, 501.0, 300.0, 200.0)
        );
        assert_eq!(
            (c.camera.width, c.camera.height, c.camera.distortion.k1),
            (320, 240, 0.1)
        );
        let c = CameraConfig::parse_config("preset = tum_fr2\ndepth_factor = 1000\n", p).unwrap();
        assert_eq!((c.camera.fx, c.depth_factor), (520.9, 1000.0));
        let e = CameraConfig::parse_config("fx = 1\nfy = x\n", p)
            .unwrap_err()
            .to_string();
        assert!(
            e.starts_with("cam.cfg:2:") && e.contains("not a number"),
            "{e}"
        );
        let e = CameraConfig::parse_config("fx = 1\nfoo = 2\n", p)
            .unwrap_err()
            .to_string();
        assert!(e.contains(":2:") && e.contains("unknown key"), "{e}");
        let e = CameraConfig::parse_config("fx = 1\n", p)
            .unwrap_err()
            .to_string();
        assert!(e.contains("missing key 'fy'"), "{e}");
        let e = CameraConfig::parse_config("preset=default\nfx = inf\n", p)
            .unwrap_err()
            .to_string();
        assert!(e.contains(":2:") && e.contains("not finite"), "{e}");
        let e = CameraConfig::parse_config("preset=default\nfx = -3\n", p)
            .unwrap_err()
            .to_string();
        assert!(e.contains("fx"), "{e}");
    }

    #[test]
    fn kinect_presets_carry_a_readout_and_files_set_one() {
        for (p, readout) in [
            ("tum_fr1", KINECT_READOUT),
            ("tum_fr2", KINECT_READOUT),
            ("7scenes", KINECT_READOUT),
            ("tum_fr3", 0.0),
            ("default", 0.0),
            ("icl_nuim", 0.0),
            ("replica", 0.0),
        ] {
            assert_eq!(
                CameraConfig::preset(p).unwrap().camera.readout,
                readout,
                "{p}"
            );
        }
        let p = Path::new("cam.cfg");
        let c = CameraConfig::parse_config(
            "preset = tum_fr1
readout = 0
",
            p,
        )
        .unwrap();
        assert_eq!(c.camera.readout, 0.0);
        let c = CameraConfig::parse_config(
            "preset = tum_fr3
readout = 0.02
",
            p,
        )
        .unwrap();
        assert_eq!(c.camera.readout, 0.02);
        let e = CameraConfig::parse_config(
            "preset = default
readout = -0.01
",
            p,
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("readout") && e.contains("cam.cfg"), "{e}");
    }
}
