//! Camera files in OpenCV's YAML dialect as ORB-SLAM2 and ORB-SLAM3 write them
//! (`Camera.fx` ... `DepthMapFactor`; ORB-SLAM3's `Camera1.fx` and `RGBD.DepthMapFactor`).
//!
//! OpenCV writes a `%YAML:1.0` directive and `!!opencv-matrix` tags that standard YAML parsers
//! reject; both are removed before the text goes to the YAML parser.

use std::collections::BTreeMap;
use std::path::Path;

use super::config::{CameraConfig, TUM_DEPTH_FACTOR};
use super::IoError;
use crate::camera::{BrownConrady, PinholeCamera};

/// OpenCV's YAML made standard: the `%YAML:1.0` directive (OpenCV's colon spelling) and
/// `!!opencv-*` tags dropped, line numbers kept.
fn standard_yaml(text: &str) -> String {
    let text = text.strip_prefix('\u{feff}').unwrap_or(text);
    text.lines()
        .map(|l| {
            if l.trim_start().starts_with("%YAML") {
                String::new()
            } else if let Some(i) = l.find("!!opencv-") {
                let rest = &l[i..];
                let end = rest.find(char::is_whitespace).unwrap_or(rest.len());
                format!("{}{}", &l[..i], &rest[end..])
            } else {
                l.to_string()
            }
        })
        .collect::<Vec<_>>()
        .join("\n")
}

/// A number of the file: YAML numbers, or numbers written as strings.
fn number(v: &serde_json::Value) -> Option<f64> {
    match v {
        serde_json::Value::Number(n) => n.as_f64(),
        serde_json::Value::String(s) => s.trim().parse().ok(),
        _ => None,
    }
}

impl CameraConfig {
    /// Reads an OpenCV / ORB-SLAM YAML camera file (chosen for `.yaml` and `.yml` files by
    /// [`CameraConfig::from_name_or_path`]).
    pub fn from_opencv_yaml(path: &Path) -> Result<CameraConfig, IoError> {
        let text = super::read_text(path)?;
        Self::parse_opencv_yaml(&text, path)
    }

    /// Parses the text of an OpenCV / ORB-SLAM YAML camera file; `path` is only used in
    /// errors. Intrinsics `fx fy cx cy` (pixels), image `width height`, distortion `k1 k2 p1
    /// p2 [k3]` (absent = none) under `Camera.` (ORB-SLAM2) or `Camera1.` (ORB-SLAM3; image
    /// size under `Camera.`), and the depth factor (raw units per metre) from `DepthMapFactor`
    /// or `RGBD.DepthMapFactor` (absent = 5000). Only pinhole cameras (`Camera.type` absent or
    /// `PinHole`) are accepted.
    pub fn parse_opencv_yaml(text: &str, path: &Path) -> Result<CameraConfig, IoError> {
        let bad = |message: String| IoError::Malformed {
            path: path.into(),
            message,
        };
        let map: BTreeMap<String, serde_json::Value> = serde_saphyr::from_str(&standard_yaml(text))
            .map_err(|e| bad(format!("not a YAML mapping of camera keys: {e}")))?;
        if let Some(t) = map.get("Camera.type").and_then(|v| v.as_str()) {
            if !t.eq_ignore_ascii_case("pinhole") {
                return Err(bad(format!(
                    "Camera.type is {t}; only PinHole cameras are read"
                )));
            }
        }
        // ORB-SLAM3 names the first camera `Camera1`; ORB-SLAM2 names it `Camera`.
        let prefix = if map.contains_key("Camera1.fx") {
            "Camera1"
        } else {
            "Camera"
        };
        let get = |keys: &[String]| -> Result<Option<f64>, IoError> {
            for k in keys {
                if let Some(v) = map.get(k) {
                    return number(v)
                        .filter(|x| x.is_finite())
                        .map(Some)
                        .ok_or_else(|| bad(format!("{k} is not a finite number ({v})")));
                }
            }
            Ok(None)
        };
        let need = |name: &str| -> Result<f64, IoError> {
            let keys = [format!("{prefix}.{name}"), format!("Camera.{name}")];
            get(&keys)?.ok_or_else(|| bad(format!("missing {}", keys[0])))
        };
        let size = |name: &str| -> Result<u32, IoError> {
            let v = need(name)?;
            if (1.0..=65535.0).contains(&v) && v.fract() == 0.0 {
                Ok(v as u32)
            } else {
                Err(bad(format!(
                    "Camera.{name} = {v} is not an image size in pixels"
                )))
            }
        };
        let mut camera = PinholeCamera::new(
            need("fx")?,
            need("fy")?,
            need("cx")?,
            need("cy")?,
            size("width")?,
            size("height")?,
        );
        let opt = |name: &str| get(&[format!("{prefix}.{name}")]);
        camera.distortion = BrownConrady {
            k1: opt("k1")?.unwrap_or(0.0),
            k2: opt("k2")?.unwrap_or(0.0),
            p1: opt("p1")?.unwrap_or(0.0),
            p2: opt("p2")?.unwrap_or(0.0),
            k3: opt("k3")?.unwrap_or(0.0),
        };
        let depth_factor = get(&["RGBD.DepthMapFactor".into(), "DepthMapFactor".into()])?
            .unwrap_or(TUM_DEPTH_FACTOR);
        let cfg = CameraConfig {
            camera,
            depth_factor,
            source: path.display().to_string(),
        };
        cfg.validate(path)?;
        Ok(cfg)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const ORB_SLAM2_TUM1: &str = "%YAML:1.0

# Camera calibration and distortion parameters (OpenCV)
Camera.fx: 517.306408
Camera.fy: 516.469215
Camera.cx: 318.643040
Camera.cy: 255.313989

Camera.k1: 0.262383
Camera.k2: -0.953104
Camera.p1: -0.005358
Camera.p2: 0.002628
Camera.k3: 1.163314

Camera.width: 640
Camera.height: 480

# Camera frames per second
Camera.fps: 30.0

# IR projector baseline times fx (aprox.)
Camera.bf: 40.0

# Color order of the images (0: BGR, 1: RGB. It is ignored if images are grayscale)
Camera.RGB: 1

# Deptmap values factor
DepthMapFactor: 5000.0

ORBextractor.nFeatures: 1000
";

    const ORB_SLAM3: &str = "%YAML:1.0
File.version: \"1.0\"
Camera.type: \"PinHole\"
Camera1.fx: 535.4
Camera1.fy: 539.2
Camera1.cx: 320.1
Camera1.cy: 247.6
Camera1.k1: 0.0
Camera1.k2: 0.0
Camera1.p1: 0.0
Camera1.p2: 0.0
Camera.width: 640
Camera.height: 480
Camera.fps: 30
Camera.RGB: 1
Stereo.ThDepth: 40.0
Stereo.b: 0.07732
RGBD.DepthMapFactor: 1000.0
IMU.T_b_c1: !!opencv-matrix
   rows: 4
   cols: 4
   dt: f
   data: [1.0, 0.0, 0.0, 0.0,
          0.0, 1.0, 0.0, 0.0,
          0.0, 0.0, 1.0, 0.0,
          0.0, 0.0, 0.0, 1.0]
";

    #[test]
    fn orb_slam2_and_orb_slam3_files_are_read() {
        let c = CameraConfig::parse_opencv_yaml(ORB_SLAM2_TUM1, Path::new("TUM1.yaml")).unwrap();
        assert_eq!((c.camera.fx, c.camera.cy), (517.306408, 255.313989));
        assert_eq!((c.camera.width, c.camera.height), (640, 480));
        assert_eq!(c.camera.distortion.k3, 1.163314);
        assert_eq!(c.depth_factor, 5000.0);
        let c = CameraConfig::parse_opencv_yaml(ORB_SLAM3, Path::new("TUM3.yaml")).unwrap();
        assert_eq!((c.camera.fx, c.camera.fy), (535.4, 539.2));
        assert_eq!(c.depth_factor, 1000.0);
        assert!(c.camera.distortion.is_zero());
    }

    #[test]
    fn missing_and_wrong_values_are_named() {
        let no_fy = ORB_SLAM2_TUM1.replace("Camera.fy: 516.469215\n", "");
        let e = CameraConfig::parse_opencv_yaml(&no_fy, Path::new("c.yaml")).unwrap_err();
        assert!(e.to_string().contains("missing Camera.fy"), "{e}");
        let text = ORB_SLAM2_TUM1.replace("Camera.width: 640", "Camera.width: 64.5");
        let e = CameraConfig::parse_opencv_yaml(&text, Path::new("c.yaml")).unwrap_err();
        assert!(e.to_string().contains("Camera.width = 64.5"), "{e}");
        let text = ORB_SLAM2_TUM1.replace("Camera.fx: 517.306408", "Camera.fx: fast");
        let e = CameraConfig::parse_opencv_yaml(&text, Path::new("c.yaml")).unwrap_err();
        assert!(
            e.to_string().contains("Camera.fx is not a finite number"),
            "{e}"
        );
        let fisheye = ORB_SLAM3.replace("\"PinHole\"", "\"KannalaBrandt8\"");
        let e = CameraConfig::parse_opencv_yaml(&fisheye, Path::new("c.yaml")).unwrap_err();
        assert!(e.to_string().contains("KannalaBrandt8"), "{e}");
        let e = CameraConfig::parse_opencv_yaml("- a\n- b\n", Path::new("c.yaml")).unwrap_err();
        assert!(
            e.to_string().starts_with("c.yaml: not a YAML mapping"),
            "{e}"
        );
    }
}
