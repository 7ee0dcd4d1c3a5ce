//! Image-only sequences and camera files for monocular SLAM.
//!
//! A sequence folder holds, in this order of precedence:
//! - an EuRoC / TUM-VI camera folder (the ASL format: `data.csv` with nanosecond time stamps,
//!   images under `data/`, the camera in `sensor.yaml`), as the folder itself, its `cam0/` or
//!   its `mav0/cam0/`; images are resampled onto an undistorted camera as they load, and
//!   [`ImageSequence::camera`] is that camera;
//! - an `rgb.txt` list (TUM style: `timestamp path` per line, `#` comments, paths relative to
//!   the folder);
//! - images (`.png`, `.jpg`, `.jpeg`) whose file stem is their time stamp in seconds
//!   (`1305031102.175304.png`).
//!
//! Images are converted to grey intensity in `[0, 255]`.
//!
//! Camera files ([`load_camera`]): JSON, either the `camera.json` written by `rgbid synth`
//! (`{"Unified": {...}}` or `{"Pinhole": {...}}`) or a bare [`UnifiedCamera`] object; or a
//! text file with one line `xi gamma cx cy width height` (optionally followed by the
//! field-of-view radius and the inner blind radius, pixels). A pinhole camera becomes the
//! unified model with `xi = 0`; it must have `fx == fy` and no distortion.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use super::asl::{self, Rectifier};
use super::MonoError;
use crate::camera::UnifiedCamera;
use crate::image::{rgb_to_intensity, ImageF32};
use crate::synth::CameraModel;

/// An image-only sequence: time-stamped image paths, sorted by time.
#[derive(Clone, Debug)]
pub struct ImageSequence {
    /// The folder.
    pub dir: PathBuf,
    /// `(timestamp seconds, image path)`, increasing in time.
    pub frames: Vec<(f64, PathBuf)>,
    /// The camera the folder states (an ASL folder's `sensor.yaml`, undistorted), `None` when
    /// the folder has no camera description.
    pub camera: Option<UnifiedCamera>,
    /// Resampling of an ASL folder's images onto [`Self::camera`].
    rectifier: Option<Arc<Rectifier>>,
}

fn is_image(p: &Path) -> bool {
    p.extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| matches!(e.to_ascii_lowercase().as_str(), "png" | "jpg" | "jpeg"))
}

impl ImageSequence {
    /// Opens a sequence folder (see the module docs).
    pub fn open(dir: &Path) -> Result<ImageSequence, MonoError> {
        let meta = std::fs::metadata(dir).map_err(|e| MonoError::File {
            path: dir.to_path_buf(),
            source: e,
        })?;
        if !meta.is_dir() {
            return Err(MonoError::File {
                path: dir.to_path_buf(),
                source: std::io::Error::other("not a folder"),
            });
        }
        let list = dir.join("rgb.txt");
        let mut frames = Vec::new();
        let mut rectifier = None;
        if let Some(cam) = asl::camera_folder(dir) {
            frames = asl::read_data_csv(&cam)?;
            let yaml = cam.join("sensor.yaml");
            if yaml.is_file() {
                rectifier = Some(Arc::new(Rectifier::new(&asl::read_sensor_yaml(&yaml)?)?));
            }
        } else if list.is_file() {
            let text = std::fs::read_to_string(&list).map_err(|e| MonoError::File {
                path: list.clone(),
                source: e,
            })?;
            for (k, line) in text.lines().enumerate() {
                let line = line.trim();
                if line.is_empty() || line.starts_with('#') {
                    continue;
                }
                let mut it = line.split_whitespace();
                let (Some(t), Some(p)) = (it.next(), it.next()) else {
                    return Err(MonoError::Parse {
                        path: list.clone(),
                        line: k + 1,
                        message: "expected 'timestamp path'".into(),
                    });
                };
                let t: f64 = t.parse().map_err(|_| MonoError::Parse {
                    path: list.clone(),
                    line: k + 1,
                    message: format!("time stamp '{t}' is not a number"),
                })?;
                if !t.is_finite() {
                    return Err(MonoError::Parse {
                        path: list.clone(),
                        line: k + 1,
                        message: "time stamp is not finite".into(),
                    });
                }
                frames.push((t, dir.join(p)));
            }
        } else {
            let rd = std::fs::read_dir(dir).map_err(|e| MonoError::File {
                path: dir.to_path_buf(),
                source: e,
            })?;
            for entry in rd.flatten() {
                let p = entry.path();
                if !is_image(&p) {
                    continue;
                }
                if let Some(t) = p
                    .file_stem()
                    .and_then(|s| s.to_str())
                    .and_then(|s| s.parse::<f64>().ok())
                    .filter(|t| t.is_finite())
                {
                    frames.push((t, p));
                }
            }
        }
        if frames.is_empty() {
            return Err(MonoError::NoImages {
                path: dir.to_path_buf(),
            });
        }
        frames.sort_by(|a, b| a.0.total_cmp(&b.0));
        for w in frames.windows(2) {
            if !(w[1].0 > w[0].0) {
                return Err(MonoError::NonIncreasingTime {
                    timestamp: w[1].0,
                    previous: w[0].0,
                });
            }
        }
        Ok(ImageSequence {
            dir: dir.to_path_buf(),
            frames,
            camera: rectifier.as_ref().map(|r| r.camera()),
            rectifier,
        })
    }

    /// Number of frames.
    pub fn len(&self) -> usize {
        self.frames.len()
    }

    /// True when there are no frames (never after a successful [`Self::open`]).
    pub fn is_empty(&self) -> bool {
        self.frames.is_empty()
    }

    /// Loads frame `index` as grey intensity (resampled onto [`Self::camera`] for an ASL
    /// folder); `None` past the end.
    pub fn load(&self, index: usize) -> Option<Result<(f64, ImageF32), MonoError>> {
        let (t, p) = self.frames.get(index)?;
        let img = load_grey(p);
        Some(match (&self.rectifier, img) {
            (Some(r), Ok(img)) => r.apply(&img, p).map(|img| (*t, img)),
            (_, img) => img.map(|img| (*t, img)),
        })
    }
}

/// Loads an image file as grey intensity in `[0, 255]`.
pub fn load_grey(path: &Path) -> Result<ImageF32, MonoError> {
    let bytes = std::fs::read(path).map_err(|e| MonoError::File {
        path: path.to_path_buf(),
        source: e,
    })?;
    let img = image::load_from_memory(&bytes).map_err(|e| MonoError::Decode {
        path: path.to_path_buf(),
        message: e.to_string(),
    })?;
    let rgb = img.to_rgb8();
    let (w, h) = (rgb.width() as usize, rgb.height() as usize);
    let data = rgb
        .pixels()
        .map(|p| rgb_to_intensity(p.0[0], p.0[1], p.0[2]))
        .collect();
    ImageF32::from_vec(w, h, data).ok_or_else(|| MonoError::Decode {
        path: path.to_path_buf(),
        message: "pixel count does not match the size".into(),
    })
}

/// The unified model of a pinhole camera (`xi = 0`); an error for distortion or `fx != fy`.
pub fn unified_from_model(model: &CameraModel) -> Result<UnifiedCamera, MonoError> {
    let cam = match model {
        CameraModel::Unified(c) => *c,
        CameraModel::Pinhole(p) => {
            let d = p.distortion;
            if [d.k1, d.k2, d.p1, d.p2, d.k3].iter().any(|v| *v != 0.0) {
                return Err(MonoError::Camera(
                    "pinhole cameras with distortion are not supported; undistort first".into(),
                ));
            }
            if (p.fx - p.fy).abs() > 1e-6 * p.fx.abs() {
                return Err(MonoError::Camera(format!(
                    "the unified model needs fx == fy (got {} and {})",
                    p.fx, p.fy
                )));
            }
            UnifiedCamera::new(0.0, p.fx, p.cx, p.cy, p.width, p.height)
        }
    };
    cam.validate()
        .map_err(|e| MonoError::Camera(e.to_string()))?;
    Ok(cam)
}

/// Reads a camera file (see the module docs).
pub fn load_camera(path: &Path) -> Result<UnifiedCamera, MonoError> {
    let text = std::fs::read_to_string(path).map_err(|e| MonoError::File {
        path: path.to_path_buf(),
        source: e,
    })?;
    parse_camera(&text, path)
}

/// Parses the text of a camera file; `path` is for messages.
pub fn parse_camera(text: &str, path: &Path) -> Result<UnifiedCamera, MonoError> {
    let trimmed = text.trim_start();
    if trimmed.starts_with('{') {
        if let Ok(model) = serde_json::from_str::<CameraModel>(text) {
            return unified_from_model(&model);
        }
        let cam: UnifiedCamera = serde_json::from_str(text).map_err(|e| MonoError::Parse {
            path: path.to_path_buf(),
            line: e.line(),
            message: format!("not a camera model: {e}"),
        })?;
        cam.validate()
            .map_err(|e| MonoError::Camera(e.to_string()))?;
        return Ok(cam);
    }
    for (k, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let v: Result<Vec<f64>, _> = line.split_whitespace().map(str::parse::<f64>).collect();
        let v = v.map_err(|_| MonoError::Parse {
            path: path.to_path_buf(),
            line: k + 1,
            message: "expected numbers 'xi gamma cx cy width height [fov_radius [inner_radius]]'"
                .into(),
        })?;
        if !(6..=8).contains(&v.len()) {
            return Err(MonoError::Parse {
                path: path.to_path_buf(),
                line: k + 1,
                message: format!("expected 6 to 8 numbers, found {}", v.len()),
            });
        }
        let size = |x: f64| {
            (x.fract() == 0.0 && (1.0..=65535.0).contains(&x))
                .then_some(x as u32)
                .ok_or_else(|| MonoError::Parse {
                    path: path.to_path_buf(),
                    line: k + 1,
                    message: format!("image size {x} must be a positive integer"),
                })
        };
        let mut cam = UnifiedCamera::new(v[0], v[1], v[2], v[3], size(v[4])?, size(v[5])?);
        cam.fov_radius = v.get(6).copied();
        cam.inner_radius = v.get(7).copied();
        cam.validate()
            .map_err(|e| MonoError::Camera(e.to_string()))?;
        return Ok(cam);
    }
    Err(MonoError::Parse {
        path: path.to_path_buf(),
        line: 0,
        message: "empty camera file".into(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn camera_files_parse_and_reject_garbage() {
        let p = Path::new("cam.txt");
        let c = parse_camera("# omni\n0.9 120 199.5 199.5 400 400 188 32\n", p).unwrap();
        assert_eq!((c.xi, c.width, c.fov_radius), (0.9, 400, Some(188.0)));
        let json =
            serde_json::to_string(&CameraModel::Unified(UnifiedCamera::catadioptric(400, 400)))
                .unwrap();
        assert_eq!(
            parse_camera(&json, p).unwrap(),
            UnifiedCamera::catadioptric(400, 400)
        );
        let pin = crate::camera::PinholeCamera::new(300.0, 300.0, 159.5, 119.5, 320, 240);
        let json = serde_json::to_string(&CameraModel::Pinhole(pin)).unwrap();
        assert_eq!(parse_camera(&json, p).unwrap().xi, 0.0);
        let bad = crate::camera::PinholeCamera::new(300.0, 310.0, 159.5, 119.5, 320, 240);
        let json = serde_json::to_string(&CameraModel::Pinhole(bad)).unwrap();
        assert!(matches!(parse_camera(&json, p), Err(MonoError::Camera(_))));
        assert!(matches!(
            parse_camera("0.9 120 1 2 400", p),
            Err(MonoError::Parse { .. })
        ));
        assert!(matches!(
            parse_camera("a b c", p),
            Err(MonoError::Parse { .. })
        ));
        assert!(matches!(
            parse_camera("0.9 120 1 2 400.5 400", p),
            Err(MonoError::Parse { .. })
        ));
        assert!(matches!(
            parse_camera("-1 120 1 2 400 400", p),
            Err(MonoError::Camera(_))
        ));
        assert!(matches!(
            parse_camera("{\"x\": 1}", p),
            Err(MonoError::Parse { .. })
        ));
        assert!(matches!(parse_camera("", p), Err(MonoError::Parse { .. })));
    }
}
