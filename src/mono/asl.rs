//! Camera folders of the ASL dataset format (EuRoC MAV, TUM-VI): `data.csv` (`#timestamp
//! [ns],filename`, images under `data/`) and `sensor.yaml` (Kalibr's camera description:
//! `camera_model: pinhole`, `intrinsics: [fu, fv, cu, cv]`, `distortion_model:
//! radial-tangential | equidistant`, `distortion_coefficients`, `resolution: [w, h]`).
//!
//! The monocular filter works with the unified model without distortion, so images of such a
//! folder are resampled as they load onto an ideal camera of the same size: a pinhole camera
//! (`xi = 0`) with the mean focal length for radial-tangential distortion (EuRoC), and a
//! stereographic one (`xi = 1`, the same resolution at the centre) for the equidistant fisheye
//! model (TUM-VI), which a pinhole cannot hold. Pixels whose source falls outside the image
//! are outside the target camera's `fov_radius`.

use std::path::{Path, PathBuf};

use glam::{DVec2, DVec3};
use rayon::prelude::*;

use super::MonoError;
use crate::camera::UnifiedCamera;
use crate::image::ImageF32;

/// The camera folder of an ASL layout under `dir`: `dir` itself when it holds `data.csv` and
/// `data/`, else `dir/cam0`, else `dir/mav0/cam0`.
pub(crate) fn camera_folder(dir: &Path) -> Option<PathBuf> {
    [
        dir.to_path_buf(),
        dir.join("cam0"),
        dir.join("mav0").join("cam0"),
    ]
    .into_iter()
    .find(|d| d.join("data.csv").is_file() && d.join("data").is_dir())
}

/// Reads `data.csv`: `(seconds, image path)` per row, paths under `data/`.
pub(crate) fn read_data_csv(cam: &Path) -> Result<Vec<(f64, PathBuf)>, MonoError> {
    let path = cam.join("data.csv");
    let text = crate::io::read_text(&path).map_err(|e| MonoError::Parse {
        path: path.clone(),
        line: 0,
        message: e.to_string(),
    })?;
    let mut frames = Vec::new();
    for (k, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let bad = |message: String| MonoError::Parse {
            path: path.clone(),
            line: k + 1,
            message,
        };
        let mut it = line.split(',').map(str::trim);
        let (Some(ns), Some(file), None) = (it.next(), it.next(), it.next()) else {
            return Err(bad("expected 'timestamp [ns],filename'".into()));
        };
        let ns: u64 = ns.parse().map_err(|_| {
            bad(format!(
                "time stamp '{ns}' is not a whole number of nanoseconds"
            ))
        })?;
        if file.is_empty() || Path::new(file).is_absolute() || file.contains("..") {
            return Err(bad(format!(
                "file name '{file}' must be a plain name inside data/"
            )));
        }
        frames.push((ns as f64 * 1e-9, cam.join("data").join(file)));
    }
    Ok(frames)
}

/// Lens model of a `sensor.yaml`.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Distortion {
    /// `radial-tangential`: `k1 k2 p1 p2` (Brown-Conrady without k3).
    RadTan([f64; 4]),
    /// `equidistant`: Kannala-Brandt `k1..k4` on the angle from the optical axis.
    Equidistant([f64; 4]),
}

/// A camera as `sensor.yaml` describes it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct SensorCamera {
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
    width: u32,
    height: u32,
    distortion: Distortion,
}

#[derive(serde::Deserialize)]
struct SensorYaml {
    camera_model: Option<String>,
    intrinsics: Vec<f64>,
    distortion_model: Option<String>,
    distortion_coefficients: Option<Vec<f64>>,
    resolution: Vec<f64>,
}

/// Reads a `sensor.yaml` (unknown keys such as `T_BS` and `rate_hz` are ignored).
pub(crate) fn read_sensor_yaml(path: &Path) -> Result<SensorCamera, MonoError> {
    let text = crate::io::read_text(path).map_err(|e| MonoError::Parse {
        path: path.to_path_buf(),
        line: 0,
        message: e.to_string(),
    })?;
    parse_sensor_yaml(&text, path)
}

/// Parses the text of a `sensor.yaml`; `path` is for messages.
pub(crate) fn parse_sensor_yaml(text: &str, path: &Path) -> Result<SensorCamera, MonoError> {
    let bad = |message: String| MonoError::Parse {
        path: path.to_path_buf(),
        line: 0,
        message,
    };
    // OpenCV-style files start with `%YAML:1.0`, which YAML parsers reject.
    let text: String = text
        .lines()
        .map(|l| {
            if l.trim_start().starts_with("%YAML") {
                ""
            } else {
                l
            }
        })
        .collect::<Vec<_>>()
        .join("\n");
    let y: SensorYaml =
        serde_saphyr::from_str(&text).map_err(|e| bad(format!("not a camera sensor.yaml: {e}")))?;
    if let Some(m) = &y.camera_model {
        if m != "pinhole" {
            return Err(bad(format!("camera_model '{m}' (only 'pinhole' is read)")));
        }
    }
    let [fx, fy, cx, cy] = y.intrinsics[..] else {
        return Err(bad(format!(
            "intrinsics: expected [fu, fv, cu, cv], found {} numbers",
            y.intrinsics.len()
        )));
    };
    if ![fx, fy].iter().all(|f| f.is_finite() && *f > 0.0)
        || ![cx, cy].iter().all(|c| c.is_finite())
    {
        return Err(bad(format!(
            "intrinsics {:?} must be finite, focal lengths > 0",
            y.intrinsics
        )));
    }
    let size = |v: f64| {
        (v.fract() == 0.0 && (1.0..=16384.0).contains(&v))
            .then_some(v as u32)
            .ok_or_else(|| {
                bad(format!(
                    "resolution {v} must be a whole number in 1..=16384"
                ))
            })
    };
    let [w, h] = y.resolution[..] else {
        return Err(bad("resolution: expected [width, height]".into()));
    };
    let coeffs = y.distortion_coefficients.unwrap_or_default();
    let four = |name: &str| -> Result<[f64; 4], MonoError> {
        match coeffs[..] {
            [] => Ok([0.0; 4]),
            [a, b, c, d] if [a, b, c, d].iter().all(|v| v.is_finite()) => Ok([a, b, c, d]),
            _ => Err(bad(format!(
                "distortion_coefficients: {name} takes 4 finite numbers, found {:?}",
                coeffs
            ))),
        }
    };
    let distortion = match y.distortion_model.as_deref().unwrap_or("radial-tangential") {
        "radial-tangential" | "radtan" | "none" => Distortion::RadTan(four("radial-tangential")?),
        "equidistant" => Distortion::Equidistant(four("equidistant")?),
        other => {
            return Err(bad(format!(
                "distortion_model '{other}' (read: radial-tangential, equidistant)"
            )))
        }
    };
    Ok(SensorCamera {
        fx,
        fy,
        cx,
        cy,
        width: size(w)?,
        height: size(h)?,
        distortion,
    })
}

impl SensorCamera {
    /// Pixel of a ray (camera frame) in the sensor's own image; `None` behind the lens.
    fn project(&self, ray: DVec3) -> Option<DVec2> {
        let (x, y) = match self.distortion {
            Distortion::RadTan([k1, k2, p1, p2]) => {
                if ray.z <= 1e-9 {
                    return None;
                }
                let (x, y) = (ray.x / ray.z, ray.y / ray.z);
                let r2 = x * x + y * y;
                let radial = 1.0 + k1 * r2 + k2 * r2 * r2;
                (
                    x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
                    y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y,
                )
            }
            Distortion::Equidistant([k1, k2, k3, k4]) => {
                let r = ray.x.hypot(ray.y);
                let theta = r.atan2(ray.z);
                if r < 1e-12 {
                    (0.0, 0.0)
                } else {
                    let t2 = theta * theta;
                    let td = theta * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))));
                    (td * ray.x / r, td * ray.y / r)
                }
            }
        };
        Some(DVec2::new(self.fx * x + self.cx, self.fy * y + self.cy))
    }

    /// The undistorted camera images are resampled onto (see the module docs).
    fn ideal(&self) -> UnifiedCamera {
        let f = 0.5 * (self.fx + self.fy);
        let xi = match self.distortion {
            Distortion::RadTan(_) => 0.0,
            Distortion::Equidistant(_) => 1.0,
        };
        // Near the axis the unified model's focal length is gamma / (1 + xi).
        UnifiedCamera::new(
            xi,
            f * (1.0 + xi),
            self.cx,
            self.cy,
            self.width,
            self.height,
        )
    }
}

/// Resamples a sensor's images onto its ideal camera: per target pixel, the source position.
#[derive(Clone, Debug)]
pub(crate) struct Rectifier {
    camera: UnifiedCamera,
    /// Source pixel per target pixel, row-major; NaN where the source is outside the image.
    map: Vec<[f32; 2]>,
}

impl Rectifier {
    /// Builds the map of `sensor`; the camera's `fov_radius` is the largest radius around the
    /// centre whose pixels all have a source inside the image.
    pub(crate) fn new(sensor: &SensorCamera) -> Result<Rectifier, MonoError> {
        let mut camera = sensor.ideal();
        camera
            .validate()
            .map_err(|e| MonoError::Camera(e.to_string()))?;
        let (w, h) = (sensor.width as usize, sensor.height as usize);
        // Sources on the border pixels count as inside (round-off of the unproject-project
        // round trip must not cut the image's edge away); they are clamped when sampled.
        let (tol, xmax, ymax) = (1e-6, (w - 1) as f64, (h - 1) as f64);
        let inside =
            |p: DVec2| p.x >= -tol && p.y >= -tol && p.x <= xmax + tol && p.y <= ymax + tol;
        let map: Vec<[f32; 2]> = (0..w * h)
            .into_par_iter()
            .map(|i| {
                let uv = DVec2::new((i % w) as f64, (i / w) as f64);
                match camera.unproject(uv).and_then(|ray| sensor.project(ray)) {
                    Some(p) if inside(p) => {
                        [p.x.clamp(0.0, xmax) as f32, p.y.clamp(0.0, ymax) as f32]
                    }
                    _ => [f32::NAN; 2],
                }
            })
            .collect();
        let centre = DVec2::new(camera.cx, camera.cy);
        let fov = map
            .iter()
            .enumerate()
            .filter(|(_, s)| s[0].is_nan())
            .map(|(i, _)| (DVec2::new((i % w) as f64, (i / w) as f64) - centre).length())
            .fold(f64::INFINITY, f64::min);
        if fov.is_finite() {
            camera.fov_radius = Some((fov - 1.0).max(0.0));
        }
        Ok(Rectifier { camera, map })
    }

    /// The camera of the resampled images.
    pub(crate) fn camera(&self) -> UnifiedCamera {
        self.camera
    }

    /// Resamples `img` (the sensor's size) bilinearly; pixels without a source are 0.
    pub(crate) fn apply(&self, img: &ImageF32, what: &Path) -> Result<ImageF32, MonoError> {
        let (w, h) = (self.camera.width as usize, self.camera.height as usize);
        if img.width() != w || img.height() != h {
            return Err(MonoError::ImageSize {
                what: what.display().to_string(),
                width: img.width(),
                height: img.height(),
                expected_width: w,
                expected_height: h,
            });
        }
        let src = img.data();
        let out: Vec<f32> = self
            .map
            .par_iter()
            .map(|&[x, y]| {
                if x.is_nan() {
                    return 0.0;
                }
                let (x0, y0) = (x.floor() as usize, y.floor() as usize);
                let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
                let (fx, fy) = (x - x0 as f32, y - y0 as f32);
                if fx == 0.0 && fy == 0.0 {
                    return src[y0 * w + x0];
                }
                let top = src[y0 * w + x0] * (1.0 - fx) + src[y0 * w + x1] * fx;
                let bottom = src[y1 * w + x0] * (1.0 - fx) + src[y1 * w + x1] * fx;
                top * (1.0 - fy) + bottom * fy
            })
            .collect();
        ImageF32::from_vec(w, h, out).ok_or_else(|| MonoError::Camera("resampled size".into()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const EUROC: &str = "# General sensor definitions.
sensor_type: camera
comment: VI-Sensor cam0 (MT9M034)

# Sensor extrinsics wrt. the body-frame.
T_BS:
  cols: 4
  rows: 4
  data: [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975,
         0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768,
        -0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949,
         0.0, 0.0, 0.0, 1.0]

# Camera specific definitions.
rate_hz: 20
resolution: [752, 480]
camera_model: pinhole
intrinsics: [458.654, 457.296, 367.215, 248.375] #fu, fv, cu, cv
distortion_model: radial-tangential
distortion_coefficients: [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]
";

    const TUMVI: &str = "sensor_type: camera
rate_hz: 20
resolution: [512, 512]
camera_model: pinhole
intrinsics: [190.978477, 190.973307, 254.931706, 256.897442]
distortion_model: equidistant
distortion_coefficients: [0.003482389402, 0.000715034845, -0.002053236141, 0.000202936736]
";

    #[test]
    fn euroc_and_tumvi_sensor_files_parse() {
        let e = parse_sensor_yaml(EUROC, Path::new("sensor.yaml")).expect("euroc");
        assert_eq!((e.width, e.height), (752, 480));
        assert_eq!(e.fx, 458.654);
        assert!(matches!(e.distortion, Distortion::RadTan([k1, ..]) if k1 == -0.28340811));
        let t = parse_sensor_yaml(TUMVI, Path::new("sensor.yaml")).expect("tum-vi");
        assert!(matches!(t.distortion, Distortion::Equidistant(_)));
        for (text, needle) in [
            (EUROC.replace("pinhole", "omni"), "camera_model 'omni'"),
            (
                EUROC.replace("radial-tangential", "fov"),
                "distortion_model 'fov'",
            ),
            (
                EUROC.replace("[752, 480]", "[752.5, 480]"),
                "resolution 752.5",
            ),
            (
                EUROC.replace("367.215, 248.375]", "367.215]"),
                "intrinsics: expected",
            ),
            ("a: [".to_string(), "not a camera sensor.yaml"),
        ] {
            let e = parse_sensor_yaml(&text, Path::new("s.yaml")).expect_err(needle);
            assert!(e.to_string().contains(needle), "{e}");
        }
    }

    /// The sensor models against OpenCV's `projectPoints` (radial-tangential) and
    /// `fisheye.projectPoints` (equidistant) of the same points and parameters.
    #[test]
    fn sensor_projection_matches_opencv() {
        let points = [
            (0.1, -0.05, 1.0),
            (-0.4, 0.3, 1.0),
            (0.5, 0.2, 0.8),
            (-0.2, -0.6, 1.5),
        ];
        let euroc = [
            (412.91782192, 225.59240531),
            (195.88728206, 376.51397596),
            (621.45199636, 349.80735066),
            (309.01053871, 74.29005924),
        ];
        let tumvi = [
            (273.95139394, 247.38785547),
            (184.04037882, 310.06449806),
            (360.11742337, 298.97058995),
            (230.8202874, 184.56514437),
        ];
        for (text, expected) in [(EUROC, euroc), (TUMVI, tumvi)] {
            let s = parse_sensor_yaml(text, Path::new("s")).expect("sensor");
            for ((x, y, z), (u, v)) in points.iter().zip(expected) {
                let p = s.project(DVec3::new(*x, *y, *z)).expect("in front");
                assert!((p - DVec2::new(u, v)).length() < 1e-6, "{p} vs ({u}, {v})");
            }
        }
    }

    /// A world point seen by the ideal camera at `uv` is seen by the sensor at `map[uv]`.
    fn check_map(sensor: &SensorCamera) {
        let r = Rectifier::new(sensor).expect("rectifier");
        let cam = r.camera();
        let w = sensor.width as usize;
        let mut checked = 0;
        for (x, y, z) in [
            (0.1, -0.05, 1.0),
            (-0.4, 0.3, 1.0),
            (0.5, 0.2, 0.8),
            (-0.2, -0.6, 1.5),
        ] {
            let p = DVec3::new(x, y, z);
            let uv = cam.project(p).expect("visible");
            let (u, v) = (uv.x.round(), uv.y.round());
            if !(u >= 0.0 && v >= 0.0 && u < w as f64 && v < f64::from(sensor.height)) {
                continue;
            }
            let s = r.map[v as usize * w + u as usize];
            if s[0].is_nan() {
                continue;
            }
            // The map is for the pixel centre (u, v), the projection of a nearby ray.
            let ray = cam.unproject(DVec2::new(u, v)).expect("ray");
            let expected = sensor.project(ray).expect("in front");
            assert!(
                (DVec2::new(f64::from(s[0]), f64::from(s[1])) - expected).length() < 1e-3,
                "{s:?} vs {expected}"
            );
            // And the ideal camera's pixel lies near the point's own projection.
            assert!((DVec2::new(u, v) - uv).length() <= 0.75);
            checked += 1;
        }
        assert!(checked >= 3, "only {checked} points checked");
    }

    #[test]
    fn resampling_maps_rays_to_the_sensor_pixels_that_see_them() {
        check_map(&parse_sensor_yaml(EUROC, Path::new("s")).expect("euroc"));
        check_map(&parse_sensor_yaml(TUMVI, Path::new("s")).expect("tum-vi"));
    }

    #[test]
    fn radial_distortion_moves_an_off_centre_edge_back_into_place() {
        // A vertical line at normalised x = 0.4 appears bent in a barrel-distorted image; after
        // resampling it is straight again at the ideal camera's column for x = 0.4.
        let s = parse_sensor_yaml(EUROC, Path::new("s")).expect("euroc");
        let (w, h) = (s.width as usize, s.height as usize);
        let mut data = vec![0.0f32; w * h];
        // The line's image in the sensor: project points (0.4 t, t', 1) densely, and per row
        // make every pixel right of the curve bright.
        let curve: Vec<DVec2> = (-2000..=2000)
            .filter_map(|k| s.project(DVec3::new(0.4, f64::from(k) * 0.001, 1.0)))
            .collect();
        for y in 0..h {
            let yf = y as f64;
            let Some(pair) = curve
                .windows(2)
                .find(|p| (p[0].y - yf) * (p[1].y - yf) <= 0.0)
            else {
                continue;
            };
            let t = (yf - pair[0].y) / (pair[1].y - pair[0].y);
            let x_line = pair[0].x + t * (pair[1].x - pair[0].x);
            for x in 0..w {
                if x as f64 > x_line {
                    data[y * w + x] = 255.0;
                }
            }
        }
        let r = Rectifier::new(&s).expect("rectifier");
        let cam = r.camera();
        let img = ImageF32::from_vec(w, h, data).expect("image");
        let out = r.apply(&img, Path::new("test")).expect("apply");
        let column = cam.cx + 0.4 * cam.gamma;
        for y in (60..h - 60).step_by(40) {
            let row = &out.data()[y * w..(y + 1) * w];
            let edge = row.iter().position(|v| *v > 127.0).expect("edge in row") as f64;
            assert!(
                (edge - column).abs() <= 2.0,
                "row {y}: edge at {edge}, line at {column}"
            );
        }
        let small = ImageF32::filled(10, 10, 0.0);
        assert!(matches!(
            r.apply(&small, Path::new("x.png")),
            Err(MonoError::ImageSize { .. })
        ));
    }
}
