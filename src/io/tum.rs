//! TUM RGB-D sequence folders, read one frame at a time.
//!
//! Layout: `rgb.txt` and `depth.txt` (`timestamp path` per line, `#` comments) with colour and
//! 16-bit depth images (raw units = metres x depth factor, 0 = no measurement), or an
//! `associations.txt` (`t_rgb rgb/x.png t_depth depth/y.png`) which, when present, is used
//! instead of associating the two lists by time. An optional `groundtruth.txt` holds
//! `world_from_camera` poses, and an optional `calib.txt` the camera (see [`super::config`]).
//!
//! Frames come out as [`RgbdFrame`]s: intensity in `[0, 255]` (BT.601 luma of the colour
//! image) and inverse depth in 1/m (0 = no measurement), undistorted when the camera has
//! distortion (intensity bilinear, depth nearest neighbour) so that they fit the pinhole
//! intrinsics of [`TumSequence::camera`] with zero distortion.
//!
//! Also here: helpers for loose frame pairs that are not in TUM layout ([`load_pair_frame`],
//! [`read_pose_file`], [`read_intrinsic_matrix`]).

use std::path::{Path, PathBuf};
use std::sync::Arc;

use glam::{DQuat, DVec3};

use super::config::{parse_numbers, CameraConfig};
use super::layouts::{layout_camera, list_frames, scannet_colour_camera, Layout, Truth};
use super::undistort::UndistortMap;
use super::IoError;
use crate::camera::PinholeCamera;
use crate::geometry::Se3;
use crate::image::{ColourFix, ColourImage, DepthBuffer, ImageBuffer, RgbdFrame};
use crate::trajectory::TimedPose;

/// Default tolerance when associating colour and depth time stamps, seconds.
pub const DEFAULT_MAX_TIME_DIFFERENCE: f64 = 0.02;

/// Plausible range of the median valid depth of a frame, metres; outside it the depth factor
/// is taken to be wrong.
pub const PLAUSIBLE_MEDIAN_DEPTH_M: (f64, f64) = (0.1, 20.0);

/// One frame of a sequence: its time stamp (that of the colour image) and its two images.
#[derive(Clone, Debug, PartialEq)]
pub struct SequenceEntry {
    /// Colour time stamp, seconds.
    pub timestamp: f64,
    /// Colour image path (joined to the sequence folder).
    pub rgb: PathBuf,
    /// Depth image path (joined to the sequence folder).
    pub depth: PathBuf,
}

/// How to open a sequence.
#[derive(Clone, Debug)]
pub struct OpenOptions {
    /// Largest colour/depth time-stamp difference accepted when associating `rgb.txt` with
    /// `depth.txt`, seconds (default 0.02).
    pub max_time_difference: f64,
    /// The camera; `None` uses `calib.txt` beside the sequence, else the `default` preset.
    pub camera: Option<CameraConfig>,
    /// A DROID-SLAM `calib.txt` ([`CalibFormat::Droid`](super::CalibFormat::Droid)) to take
    /// the camera from instead of `camera`: its image size is the first frame's (the depth
    /// image's for ScanNet, whose frames are on the depth camera, else the colour image's),
    /// its depth factor the layout's (TUM and ETH3D 5000, 7-Scenes and ScanNet 1000 per
    /// metre, Replica 6553.5).
    pub droid_calib: Option<PathBuf>,
    /// Keep only the first this many frames.
    pub max_frames: Option<usize>,
    /// The folder's layout; `None` detects it from the content ([`Layout::detect`]).
    pub layout: Option<Layout>,
    /// Frame rate of layouts without time stamps (7-Scenes, Replica), Hz (default 30).
    pub frame_rate: f64,
}

impl Default for OpenOptions {
    fn default() -> Self {
        Self {
            max_time_difference: DEFAULT_MAX_TIME_DIFFERENCE,
            camera: None,
            droid_calib: None,
            max_frames: None,
            layout: None,
            frame_rate: 30.0,
        }
    }
}

/// An opened RGB-D sequence folder: TUM RGB-D, or another [`Layout`] (ETH3D, 7-Scenes,
/// Replica); frames are decoded from disk on demand by [`Self::load`].
#[derive(Clone, Debug)]
pub struct TumSequence {
    /// The sequence folder.
    pub root: PathBuf,
    /// The camera of the frames that [`Self::load`] returns (already undistorted: its
    /// `distortion` is the raw images' one, which `load` removes).
    pub camera: PinholeCamera,
    /// Raw depth units per metre.
    pub depth_factor: f64,
    /// The frames, in time order.
    pub entries: Vec<SequenceEntry>,
    /// `groundtruth.txt` when the folder has one (TUM and ETH3D; see [`Self::ground_truth`]
    /// for every layout).
    pub groundtruth: Option<PathBuf>,
    /// The folder's layout.
    pub layout: Layout,
    /// Where the camera came from (preset, config file, calib.txt).
    pub camera_source: String,
    undistort: Option<Arc<UndistortMap>>,
    truth: Truth,
    colour_camera: Option<Box<PinholeCamera>>,
    depth_warning: Option<String>,
}

impl TumSequence {
    /// Opens a sequence folder: reads the lists, associates colour and depth, checks that every
    /// listed image exists, and decodes the first frame to check sizes and the depth scale.
    pub fn open(dir: &Path, opts: &OpenOptions) -> Result<TumSequence, IoError> {
        if !dir.is_dir() {
            return Err(IoError::MissingFolder { path: dir.into() });
        }
        let layout = opts.layout.unwrap_or_else(|| Layout::detect(dir));
        let own = layout_camera(layout, dir)?;
        // A DROID-SLAM calibration is sized by the first frame, which is known only once the
        // frames are listed; until then the layout's camera stands in.
        let droid_depth_factor = own
            .as_ref()
            .map_or(super::config::TUM_DEPTH_FACTOR, |c| c.depth_factor);
        let cfg = match (&opts.camera, own) {
            (Some(c), _) if opts.droid_calib.is_none() => c.clone(),
            (_, Some(c)) => c,
            (_, None) => {
                let calib = dir.join("calib.txt");
                // The folder's calib.txt may be the DROID-SLAM file itself.
                if calib.is_file() && opts.droid_calib.is_none() {
                    CameraConfig::from_calib_txt(&calib)?
                } else {
                    CameraConfig::preset("default").ok_or_else(|| IoError::UnknownCamera {
                        name: "default".into(),
                        presets: super::config::PRESETS.join(", "),
                    })?
                }
            }
        };
        cfg.validate(Path::new(&cfg.source))?;
        let droid = opts.droid_calib.as_deref();
        let mut cfg = cfg;
        log::info!(
            "{}: {layout} layout, camera from {}",
            dir.display(),
            cfg.source
        );

        let gt = dir.join("groundtruth.txt");
        let listing = match layout {
            Layout::SevenScenes | Layout::ScanNet | Layout::Replica => {
                Some(list_frames(layout, dir, opts.frame_rate, opts.max_frames)?)
            }
            Layout::Tum | Layout::Eth3d => None,
        };
        let assoc = dir.join("associations.txt");
        let (mut entries, truth) = if let Some(l) = listing {
            (l.entries, l.truth)
        } else if assoc.is_file() {
            (read_associations(dir, &assoc)?, Truth::None)
        } else {
            let (rgb_txt, depth_txt) = (dir.join("rgb.txt"), dir.join("depth.txt"));
            for p in [&rgb_txt, &depth_txt] {
                if !p.is_file() {
                    return Err(IoError::MissingFile {
                        path: p.clone(),
                        what: "image list (rgb.txt and depth.txt, or associations.txt)".into(),
                    });
                }
            }
            let rgb = read_list(dir, &rgb_txt)?;
            let depth = read_list(dir, &depth_txt)?;
            let ta: Vec<f64> = rgb.iter().map(|e| e.0).collect();
            let tb: Vec<f64> = depth.iter().map(|e| e.0).collect();
            let pairs = associate(&ta, &tb, opts.max_time_difference);
            if pairs.is_empty() {
                return Err(IoError::NoAssociations {
                    path: dir.into(),
                    max_difference: opts.max_time_difference,
                    closest: closest_difference(&ta, &tb),
                });
            }
            let entries = pairs
                .into_iter()
                .map(|(i, j)| SequenceEntry {
                    timestamp: rgb[i].0,
                    rgb: rgb[i].1.clone(),
                    depth: depth[j].1.clone(),
                })
                .collect();
            (entries, Truth::None)
        };
        let truth = match truth {
            Truth::None if gt.is_file() => Truth::TumFile(gt.clone()),
            t => t,
        };
        entries.sort_by(|a, b| a.timestamp.total_cmp(&b.timestamp));
        if let Some(n) = opts.max_frames {
            entries.truncate(n);
        }
        if entries.is_empty() {
            return Err(IoError::Empty {
                path: dir.into(),
                message: "the sequence has no frames".into(),
            });
        }
        if let Some(calib) = droid {
            let first = match layout {
                Layout::ScanNet => &entries[0].depth,
                _ => &entries[0].rgb,
            };
            let (w, h) = image::image_dimensions(first).map_err(|e| IoError::Image {
                path: first.clone(),
                message: e.to_string(),
            })?;
            cfg = CameraConfig::from_droid_calib(calib, w, h, droid_depth_factor)?;
            log::info!("camera from {} at {w} x {h}", cfg.source);
        }
        let colour_camera = match layout {
            Layout::ScanNet => {
                let first = &entries[0].rgb;
                let (w, h) = image::image_dimensions(first).map_err(|e| IoError::Image {
                    path: first.clone(),
                    message: e.to_string(),
                })?;
                Some(Box::new(scannet_colour_camera(dir, w, h)?))
            }
            _ => None,
        };
        if !cfg.camera.distortion.is_zero() {
            // The undistortion table has the camera's size (tens of bytes per pixel): the
            // first image's header must agree with the camera before the table is built.
            check_image_size(&entries[0].rgb, &cfg.camera, &cfg.source)?;
        }
        let depth_warning = depth_factor_warning(&entries, cfg.depth_factor);
        let undistort =
            (!cfg.camera.distortion.is_zero()).then(|| Arc::new(UndistortMap::new(&cfg.camera)));
        let seq = TumSequence {
            root: dir.into(),
            camera: cfg.camera,
            depth_factor: cfg.depth_factor,
            entries,
            groundtruth: matches!(truth, Truth::TumFile(_)).then_some(gt),
            layout,
            camera_source: cfg.source,
            undistort,
            truth,
            colour_camera,
            depth_warning,
        };
        seq.load(0)?;
        Ok(seq)
    }

    /// A warning when the depth factor looks wrong for the sensor's range: in at least half
    /// of a few frames spread over the sequence, many valid depths fall outside [`SENSOR_RANGE_M`] at
    /// [`Self::depth_factor`]; the message names an image and the common factor that would
    /// fit. Frames still load (a scene can be unusual); the caller reports it.
    pub fn depth_range_warning(&self) -> Option<&str> {
        self.depth_warning.as_deref()
    }

    /// Number of frames.
    pub fn len(&self) -> usize {
        self.entries.len()
    }

    /// The sequence's ground truth (`world_from_camera` with time stamps), when its layout
    /// has one: `groundtruth.txt` (TUM, ETH3D), the per-frame pose files (7-Scenes) or
    /// `traj.txt` (Replica).
    pub fn ground_truth(&self) -> Result<Option<Vec<TimedPose>>, IoError> {
        self.truth.read(&self.entries)
    }

    /// True when there are no frames (never after a successful [`Self::open`]).
    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    /// The camera of the loaded (undistorted) frames: [`Self::camera`] without distortion.
    pub fn undistorted_camera(&self) -> PinholeCamera {
        let mut c = self.camera;
        c.distortion = Default::default();
        c
    }

    /// Decodes frame `index` from disk: intensity and inverse depth (1/m), undistorted.
    pub fn load(&self, index: usize) -> Result<RgbdFrame, IoError> {
        let e = self.entries.get(index).ok_or(IoError::IndexOutOfRange {
            index,
            len: self.entries.len(),
        })?;
        let cam = CameraRef {
            camera: &self.camera,
            source: &self.camera_source,
            colour: self.colour_camera.as_deref(),
        };
        let remap = match &self.undistort {
            Some(m) => Remap::Cpu(m),
            None => Remap::None,
        };
        decode_frame(&e.rgb, &e.depth, cam, self.depth_factor, remap, e.timestamp)
    }
}

/// One frame of a sequence folder as stored on disk: the colour image's bytes (grey or RGB,
/// not undistorted, at the colour camera's size) and the raw 16-bit depth (units of `1 / depth_factor` metres, 0 = no
/// measurement), both row-major. What bindings hand to their users unchanged.
#[derive(Clone, Debug)]
pub struct RawFrame {
    /// Time stamp of the colour image, seconds.
    pub timestamp: f64,
    /// Width of the colour image in pixels.
    pub width: usize,
    /// Height of the colour image in pixels.
    pub height: usize,
    /// The colour image's pixels.
    pub pixels: RawPixels,
    /// Raw depth at the depth camera's size (that of the sequence's camera; the colour
    /// image's size except for ScanNet).
    pub depth: Vec<u16>,
}

impl TumSequence {
    /// Decodes frame `index` as stored ([`RawFrame`]): no conversion to intensity or inverse
    /// depth and no undistortion. Sizes are checked against each other and the camera.
    pub fn load_raw(&self, index: usize) -> Result<RawFrame, IoError> {
        let e = self.entries.get(index).ok_or(IoError::IndexOutOfRange {
            index,
            len: self.entries.len(),
        })?;
        let (rgb, depth) = rayon::join(|| decode_colour(&e.rgb), || decode_depth(&e.depth));
        let (rgb, depth) = (rgb?, depth?);
        // A layout whose colour camera is not the depth camera (ScanNet) keeps its colour
        // image at its own size.
        if self.colour_camera.is_none() && (rgb.width, rgb.height) != (depth.width, depth.height) {
            return Err(IoError::ImageSizeMismatch {
                rgb: e.rgb.clone(),
                rgb_size: (rgb.width as u32, rgb.height as u32),
                depth: e.depth.clone(),
                depth_size: (depth.width as u32, depth.height as u32),
            });
        }
        let camera_size = (self.camera.width, self.camera.height);
        if (depth.width as u32, depth.height as u32) != camera_size {
            return Err(IoError::CameraSizeMismatch {
                path: e.depth.clone(),
                image_size: (depth.width as u32, depth.height as u32),
                camera_size,
                camera_source: self.camera_source.clone(),
            });
        }
        Ok(RawFrame {
            timestamp: e.timestamp,
            width: rgb.width,
            height: rgb.height,
            pixels: rgb.pixels,
            depth: depth.raw,
        })
    }
}

/// Checks an image's size, read from its header alone, against the camera's.
fn check_image_size(path: &Path, camera: &PinholeCamera, source: &str) -> Result<(), IoError> {
    let image_size = image::image_dimensions(path).map_err(|e| IoError::Image {
        path: path.into(),
        message: e.to_string(),
    })?;
    let camera_size = (camera.width, camera.height);
    if image_size != camera_size {
        return Err(IoError::CameraSizeMismatch {
            path: path.into(),
            image_size,
            camera_size,
            camera_source: source.into(),
        });
    }
    Ok(())
}

/// Loads one colour + 16-bit depth pair that is not part of a TUM folder (time stamp 0),
/// undistorting it when `camera` has distortion. Checks sizes against `camera` and the depth
/// scale, as [`TumSequence::load`] does.
pub fn load_pair_frame(
    rgb_path: &Path,
    depth_path: &Path,
    camera: &PinholeCamera,
    depth_factor: f64,
) -> Result<RgbdFrame, IoError> {
    let cfg = CameraConfig {
        camera: *camera,
        depth_factor,
        source: "the given camera".into(),
    };
    cfg.validate(rgb_path)?;
    let map = (!camera.distortion.is_zero()).then(|| Arc::new(UndistortMap::new(camera)));
    decode_frame(
        rgb_path,
        depth_path,
        CameraRef {
            camera,
            source: &cfg.source,
            colour: None,
        },
        depth_factor,
        map.as_ref().map_or(Remap::None, Remap::Cpu),
        0.0,
    )
}

/// Parses `tx ty tz qx qy qz qw` (a `world_from_camera` pose, metres, any-norm quaternion).
pub fn parse_pose_line(line: &str) -> Result<Se3, String> {
    let v = parse_numbers(line)?;
    if v.len() != 7 {
        return Err(format!(
            "expected 7 numbers (tx ty tz qx qy qz qw), found {}",
            v.len()
        ));
    }
    let q = DQuat::from_xyzw(v[3], v[4], v[5], v[6]);
    let n = q.length();
    if n.is_nan() || n <= 1e-6 {
        return Err("quaternion has zero length".into());
    }
    Ok(Se3::new(q / n, DVec3::new(v[0], v[1], v[2])))
}

/// Reads a pose file holding one `tx ty tz qx qy qz qw` line (e.g. `pose_prev.txt`).
pub fn read_pose_file(path: &Path) -> Result<Se3, IoError> {
    let text = super::read_text(path)?;
    for (i, line) in text.lines().enumerate() {
        let s = line.trim();
        if s.is_empty() || s.starts_with('#') {
            continue;
        }
        return parse_pose_line(s).map_err(|m| IoError::parse(path, i + 1, m));
    }
    Err(IoError::Empty {
        path: path.into(),
        message: "no pose line".into(),
    })
}

/// Reads a 3x3 intrinsic matrix (9 numbers, row-major, any whitespace) into a camera of the
/// given size without distortion.
pub fn read_intrinsic_matrix(
    path: &Path,
    width: u32,
    height: u32,
) -> Result<PinholeCamera, IoError> {
    let text = super::read_text(path)?;
    let mut v = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let s = line.split('#').next().unwrap_or("").trim();
        if !s.is_empty() {
            v.extend(parse_numbers(s).map_err(|m| IoError::parse(path, i + 1, m))?);
        }
    }
    if v.len() != 9 {
        return Err(IoError::parse(
            path,
            text.lines().count().max(1),
            format!("expected 9 numbers, found {}", v.len()),
        ));
    }
    let cam = PinholeCamera::new(v[0], v[4], v[2], v[5], width, height);
    cam.validate().map_err(|source| IoError::InvalidCamera {
        path: path.into(),
        source,
    })?;
    Ok(cam)
}

/// Associates two time-stamp lists (seconds) one-to-one as TUM's `associate.py` does: all pairs
/// within `max_difference` are considered, closest first, each stamp used at most once.
/// Returns `(index_a, index_b)` pairs sorted by `a`'s time stamp.
pub fn associate(a: &[f64], b: &[f64], max_difference: f64) -> Vec<(usize, usize)> {
    let mut bi: Vec<usize> = (0..b.len()).collect();
    bi.sort_by(|&x, &y| b[x].total_cmp(&b[y]));
    let sorted_b: Vec<f64> = bi.iter().map(|&j| b[j]).collect();
    let mut candidates = Vec::new();
    for (i, &ta) in a.iter().enumerate() {
        let start = sorted_b.partition_point(|&t| t < ta - max_difference);
        for (k, &tb) in sorted_b.iter().enumerate().skip(start) {
            if tb > ta + max_difference {
                break;
            }
            candidates.push(((ta - tb).abs(), i, bi[k]));
        }
    }
    candidates.sort_by(|x, y| x.0.total_cmp(&y.0).then(x.1.cmp(&y.1)).then(x.2.cmp(&y.2)));
    let (mut used_a, mut used_b) = (vec![false; a.len()], vec![false; b.len()]);
    let mut out = Vec::new();
    for (_, i, j) in candidates {
        if !used_a[i] && !used_b[j] {
            used_a[i] = true;
            used_b[j] = true;
            out.push((i, j));
        }
    }
    out.sort_by(|x, y| a[x.0].total_cmp(&a[y.0]).then(x.0.cmp(&y.0)));
    out
}

/// The smallest `|a_i - b_j|`, if both lists are non-empty.
fn closest_difference(a: &[f64], b: &[f64]) -> Option<f64> {
    let mut s = b.to_vec();
    s.sort_by(f64::total_cmp);
    a.iter()
        .filter_map(|&t| {
            let k = s.partition_point(|&x| x < t);
            [k.checked_sub(1), Some(k)]
                .into_iter()
                .flatten()
                .filter_map(|j| s.get(j))
                .map(|&x| (x - t).abs())
                .reduce(f64::min)
        })
        .reduce(f64::min)
}

/// Reads `timestamp path` lines; paths are joined to `root` and must exist.
fn read_list(root: &Path, list: &Path) -> Result<Vec<(f64, PathBuf)>, IoError> {
    let text = super::read_text(list)?;
    let mut out = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let s = line.trim();
        if s.is_empty() || s.starts_with('#') {
            continue;
        }
        let f: Vec<&str> = s.split_whitespace().collect();
        if f.len() < 2 {
            return Err(IoError::parse(
                list,
                i + 1,
                format!("expected `timestamp path`, found '{s}'"),
            ));
        }
        let t = parse_time(f[0]).map_err(|m| IoError::parse(list, i + 1, m))?;
        out.push((t, existing(root, f[1], list, i + 1)?));
    }
    if out.is_empty() {
        return Err(IoError::Empty {
            path: list.into(),
            message: "no entries in image list".into(),
        });
    }
    Ok(out)
}

/// Reads `t_rgb rgb_path t_depth depth_path` lines.
fn read_associations(root: &Path, list: &Path) -> Result<Vec<SequenceEntry>, IoError> {
    let text = super::read_text(list)?;
    let mut out = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let s = line.trim();
        if s.is_empty() || s.starts_with('#') {
            continue;
        }
        let f: Vec<&str> = s.split_whitespace().collect();
        if f.len() < 4 {
            return Err(IoError::parse(
                list,
                i + 1,
                format!(
                    "expected `t_rgb rgb_path t_depth depth_path`, found {} fields",
                    f.len()
                ),
            ));
        }
        let t = parse_time(f[0]).map_err(|m| IoError::parse(list, i + 1, m))?;
        parse_time(f[2]).map_err(|m| IoError::parse(list, i + 1, m))?;
        out.push(SequenceEntry {
            timestamp: t,
            rgb: existing(root, f[1], list, i + 1)?,
            depth: existing(root, f[3], list, i + 1)?,
        });
    }
    if out.is_empty() {
        return Err(IoError::Empty {
            path: list.into(),
            message: "no entries in associations file".into(),
        });
    }
    Ok(out)
}

fn parse_time(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(t) if t.is_finite() => Ok(t),
        Ok(_) => Err(format!("time stamp is not finite ({s})")),
        Err(_) => Err(format!("time stamp '{s}' is not a number")),
    }
}

fn existing(root: &Path, rel: &str, list: &Path, line: usize) -> Result<PathBuf, IoError> {
    let p = root.join(rel);
    if p.is_file() {
        Ok(p)
    } else {
        Err(IoError::MissingFile {
            path: p,
            what: format!("image listed at {}:{line}", list.display()),
        })
    }
}

/// Where a frame's undistortion runs.
#[derive(Clone, Copy)]
enum Remap<'a> {
    /// The camera has no distortion.
    None,
    /// The remap table on the CPU.
    Cpu(&'a Arc<UndistortMap>),
}

#[derive(Clone, Copy)]
struct CameraRef<'a> {
    camera: &'a PinholeCamera,
    source: &'a str,
    /// The colour images' own camera when they are not taken with `camera` (ScanNet): the
    /// colour is resampled onto `camera`'s pixels.
    colour: Option<&'a PinholeCamera>,
}

/// Decodes, checks, converts and undistorts one frame. Colour and depth decode in parallel.
fn decode_frame(
    rgb_path: &Path,
    depth_path: &Path,
    cam: CameraRef<'_>,
    depth_factor: f64,
    remap: Remap<'_>,
    timestamp: f64,
) -> Result<RgbdFrame, IoError> {
    let (rgb, depth) = rayon::join(|| decode_colour(rgb_path), || decode_depth(depth_path));
    let (rgb, depth) = (rgb?, depth?);
    let rgb = match cam.colour {
        Some(cc) if (rgb.width, rgb.height) != (depth.width, depth.height) => {
            resample_colour(&rgb, cc, cam.camera, depth.width, depth.height)
        }
        _ => rgb,
    };
    if (rgb.width, rgb.height) != (depth.width, depth.height) {
        return Err(IoError::ImageSizeMismatch {
            rgb: rgb_path.into(),
            rgb_size: (rgb.width as u32, rgb.height as u32),
            depth: depth_path.into(),
            depth_size: (depth.width as u32, depth.height as u32),
        });
    }
    let camera_size = (cam.camera.width, cam.camera.height);
    if (rgb.width as u32, rgb.height as u32) != camera_size {
        return Err(IoError::CameraSizeMismatch {
            path: rgb_path.into(),
            image_size: (rgb.width as u32, rgb.height as u32),
            camera_size,
            camera_source: cam.source.into(),
        });
    }
    if !depth.raw.iter().any(|&d| d > 0) {
        return Err(IoError::NoValidDepth {
            path: depth_path.into(),
        });
    }
    check_depth_scale(&depth.raw, depth_factor, depth_path)?;
    let image = match &rgb.pixels {
        RawPixels::Gray(g) => ImageBuffer::Gray(g),
        RawPixels::Rgb(c) => ImageBuffer::Rgb(c),
    };
    let depth_buffer = DepthBuffer::U16 {
        data: &depth.raw,
        factor: depth_factor,
    };
    let mut frame = RgbdFrame::from_buffers(timestamp, rgb.width, rgb.height, image, depth_buffer)
        .map_err(|source| IoError::Frame {
            path: rgb_path.into(),
            source,
        })?;
    match remap {
        Remap::None => {}
        Remap::Cpu(m) => {
            let mut out = vec![0.0f32; frame.intensity.data.len()];
            m.remap_bilinear(&frame.intensity.data, &mut out);
            frame.intensity.data = out;
            let mut out = vec![0.0f32; frame.inverse_depth.data.len()];
            m.remap_nearest(&frame.inverse_depth.data, &mut out);
            frame.inverse_depth.data = out;
            if let Some(c) = frame.colour.take() {
                let m = Arc::clone(m);
                let fix: ColourFix = Arc::new(move |c: &ColourImage| remap_colour(&m, c));
                frame.colour = Some(c.fixed_later(fix));
            }
        }
    }
    Ok(frame)
}

/// `colour` undistorted (bilinear, rounded to the nearest byte).
fn remap_colour(m: &UndistortMap, colour: &ColourImage) -> ColourImage {
    let mut rgb = vec![0u8; colour.rgb().len()];
    m.remap_bilinear_rgb8(colour.rgb(), &mut rgb);
    // The size is the frame's by construction.
    ColourImage::from_rgb(colour.width(), colour.height(), rgb).unwrap_or_else(|_| colour.clone())
}

fn read_image(path: &Path) -> Result<image::DynamicImage, IoError> {
    if !path.is_file() {
        return Err(IoError::MissingFile {
            path: path.into(),
            what: "image".into(),
        });
    }
    let reader = image::ImageReader::open(path)
        .map_err(|e| IoError::file(path, e))?
        .with_guessed_format()
        .map_err(|e| IoError::file(path, e))?;
    reader.decode().map_err(|e| IoError::Image {
        path: path.into(),
        message: e.to_string(),
    })
}

/// A decoded colour image: grey or RGB bytes, as stored.
struct RawImage {
    width: usize,
    height: usize,
    pixels: RawPixels,
}

/// A colour image's bytes as stored, row-major.
#[derive(Clone, Debug)]
pub enum RawPixels {
    /// One grey value per pixel.
    Gray(Vec<u8>),
    /// Interleaved R, G, B per pixel (images stored with alpha or 16 bits are converted).
    Rgb(Vec<u8>),
}

/// `rgb`, seen by `colour`, resampled (bilinear) onto the pixels of `target` (`width` x
/// `height`) by the two intrinsics: the cameras share their centre and orientation, as ScanNet's
/// colour and depth cameras do after its export. Pixels that fall outside the colour image are
/// black.
fn resample_colour(
    rgb: &RawImage,
    colour: &PinholeCamera,
    target: &PinholeCamera,
    width: usize,
    height: usize,
) -> RawImage {
    let (src, channels) = match &rgb.pixels {
        RawPixels::Gray(g) => (g, 1),
        RawPixels::Rgb(c) => (c, 3),
    };
    let mut out = vec![0u8; width * height * channels];
    for v in 0..height {
        for u in 0..width {
            let x = (u as f64 - target.cx) / target.fx;
            let y = (v as f64 - target.cy) / target.fy;
            let uc = colour.fx * x + colour.cx;
            let vc = colour.fy * y + colour.cy;
            if !(uc >= 0.0 && vc >= 0.0) {
                continue;
            }
            let (u0, v0) = (uc.floor() as usize, vc.floor() as usize);
            if u0 + 1 >= rgb.width || v0 + 1 >= rgb.height {
                continue;
            }
            let (a, b) = (uc - u0 as f64, vc - v0 as f64);
            for k in 0..channels {
                let at =
                    |uu: usize, vv: usize| f64::from(src[(vv * rgb.width + uu) * channels + k]);
                let val = (1.0 - b) * ((1.0 - a) * at(u0, v0) + a * at(u0 + 1, v0))
                    + b * ((1.0 - a) * at(u0, v0 + 1) + a * at(u0 + 1, v0 + 1));
                out[(v * width + u) * channels + k] = val.round().clamp(0.0, 255.0) as u8;
            }
        }
    }
    RawImage {
        width,
        height,
        pixels: if channels == 1 {
            RawPixels::Gray(out)
        } else {
            RawPixels::Rgb(out)
        },
    }
}

fn decode_colour(path: &Path) -> Result<RawImage, IoError> {
    use image::DynamicImage as D;
    let img = read_image(path)?;
    let (width, height) = (img.width() as usize, img.height() as usize);
    let pixels = match img {
        D::ImageLuma8(b) => RawPixels::Gray(b.into_raw()),
        D::ImageRgb8(b) => RawPixels::Rgb(b.into_raw()),
        other => RawPixels::Rgb(other.to_rgb8().into_raw()),
    };
    Ok(RawImage {
        width,
        height,
        pixels,
    })
}

struct RawDepth {
    width: usize,
    height: usize,
    raw: Vec<u16>,
}

fn decode_depth(path: &Path) -> Result<RawDepth, IoError> {
    let img = read_image(path)?;
    let (width, height) = (img.width() as usize, img.height() as usize);
    match img {
        image::DynamicImage::ImageLuma16(b) => Ok(RawDepth {
            width,
            height,
            raw: b.into_raw(),
        }),
        other => Err(IoError::DepthNot16Bit {
            path: path.into(),
            found: format!("{:?}", other.color()),
        }),
    }
}

/// Range of an RGB-D sensor of the Kinect / Xtion / Kinect v2 class, metres: they measure
/// nothing nearer than about 0.5 m and little beyond 10 m, so many depths outside it point at
/// a wrong depth factor. A 5x error keeps the median plausible but not the range: a room read
/// 5x too near has its nearest walls under 0.5 m, one read 5x too far its far walls beyond
/// 10 m. (Sensors that do measure nearer, such as a RealSense at close range, get a warning
/// that does not stop the run.)
pub const SENSOR_RANGE_M: (f64, f64) = (0.5, 10.0);
/// Share of valid depths outside [`SENSOR_RANGE_M`] above which a frame's depth factor is
/// suspect: the real sequences and generated scenes at hand have none outside it, a room
/// read 5x too near has a tenth or more under 0.5 m.
const OUT_OF_RANGE_SHARE: f64 = 0.05;

/// The warning of a sequence whose depth factor does not fit the sensor's range: frames
/// spread over the sequence (up to [`DEPTH_CHECK_FRAMES`] with enough measurements) are
/// judged one by one, and at least half of them must agree, so that one odd frame (skipped
/// when it is loaded) does not speak for the sequence.
fn depth_factor_warning(entries: &[SequenceEntry], factor: f64) -> Option<String> {
    let n = entries.len();
    let picks = DEPTH_CHECK_FRAMES.min(n);
    let mut indices: Vec<usize> = (0..picks)
        .map(|k| {
            if picks > 1 {
                k * (n - 1) / (picks - 1)
            } else {
                0
            }
        })
        .collect();
    indices.dedup();
    let verdicts: Vec<Option<String>> = indices
        .iter()
        .filter_map(|&i| {
            let d = decode_depth(&entries[i].depth).ok()?;
            enough_depths(&d.raw).then(|| {
                depth_range_warning(&d.raw, factor)
                    .map(|w| format!("{}: {w}", entries[i].depth.display()))
            })
        })
        .collect();
    let flagged: Vec<&String> = verdicts.iter().flatten().collect();
    // At least half: a view of far walls alone shows little of a room read 5x too near.
    if flagged.is_empty() || 2 * flagged.len() < verdicts.len() {
        return None;
    }
    Some(format!(
        "{} ({} of {} frames checked are like it)",
        flagged[0],
        flagged.len(),
        verdicts.len()
    ))
}

/// Frames, spread over the sequence, whose depth judges the depth factor.
const DEPTH_CHECK_FRAMES: usize = 5;

/// Valid depths of a sample needed to judge the depth factor by.
const MIN_DEPTH_SAMPLE: usize = 20;

/// The valid raw depths of a sample of at most about 16384 pixels (0 and 65535, 7-Scenes' mark
/// of no measurement, are none).
fn depth_sample(raw: &[u16]) -> Vec<f64> {
    let stride = (raw.len() / 16384).max(1);
    raw.iter()
        .step_by(stride)
        .filter(|&&d| d > 0 && d < u16::MAX)
        .map(|&d| f64::from(d))
        .collect()
}

/// Whether an image has enough valid depths for [`depth_range_warning`] to judge it.
fn enough_depths(raw: &[u16]) -> bool {
    depth_sample(raw).len() >= MIN_DEPTH_SAMPLE
}

/// A warning when many valid depths (of a sample) fall outside [`SENSOR_RANGE_M`] at
/// `factor`, naming the common factor that would put the most of them inside.
fn depth_range_warning(raw: &[u16], factor: f64) -> Option<String> {
    let sample = depth_sample(raw);
    if sample.len() < MIN_DEPTH_SAMPLE {
        return None;
    }
    let (lo, hi) = SENSOR_RANGE_M;
    let outside = |f: f64| {
        sample
            .iter()
            .filter(|&&d| !(lo..=hi).contains(&(d / f)))
            .count() as f64
            / sample.len() as f64
    };
    let share = outside(factor);
    if share <= OUT_OF_RANGE_SHARE {
        return None;
    }
    let better = [1000.0, 5000.0, 10000.0, 100.0, 10.0, 1.0]
        .into_iter()
        .filter(|&f: &f64| f != factor)
        .map(|f| (f, outside(f)))
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .filter(|&(_, s)| s < share);
    Some(format!(
        "{:.0} % of the valid depths are outside the sensor range {lo}-{hi} m at depth factor \
         {factor}{}",
        100.0 * share,
        match better {
            Some((f, s)) => format!(
                "; factor {f} would put {:.0} % inside (set depth_factor in the camera file)",
                100.0 * (1.0 - s)
            ),
            None => String::new(),
        }
    ))
}

/// Checks that the median valid depth (on a sample of pixels) is plausible for `factor`.
fn check_depth_scale(raw: &[u16], factor: f64, path: &Path) -> Result<(), IoError> {
    let stride = (raw.len() / 16384).max(1);
    let mut sample: Vec<u16> = raw
        .iter()
        .step_by(stride)
        .copied()
        .filter(|&d| d > 0 && d < u16::MAX)
        .collect();
    if sample.len() < 20 {
        return Ok(()); // too few measurements to judge; not a scale error
    }
    let mid = sample.len() / 2;
    let median_raw = f64::from(*sample.select_nth_unstable(mid).1);
    let median_m = median_raw / factor;
    let (lo, hi) = PLAUSIBLE_MEDIAN_DEPTH_M;
    if (lo..=hi).contains(&median_m) {
        return Ok(());
    }
    let suggested = [1000.0, 5000.0, 10000.0, 100.0, 10.0, 1.0]
        .into_iter()
        .filter(|&f: &f64| f != factor && (lo..=hi).contains(&(median_raw / f)))
        .min_by(|a, b| {
            (median_raw / a / 2.0)
                .ln()
                .abs()
                .total_cmp(&(median_raw / b / 2.0).ln().abs())
        });
    Err(IoError::DepthScaleMismatch {
        path: path.into(),
        factor,
        median_m,
        suggested,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A distorted camera's colour is undistorted when it is first read, as the intensity is
    /// when the frame is decoded, and the result is kept: clones made after the first read
    /// share it, clones made before undistort their own copy the same way.
    #[test]
    fn colour_is_undistorted_when_first_read() {
        let tmp = tempfile::tempdir().unwrap();
        let (w, h) = (32u32, 24u32);
        let rgb = image::RgbImage::from_fn(w, h, |x, y| {
            image::Rgb([(7 * x) as u8, (9 * y) as u8, ((x * y) % 251) as u8])
        });
        rgb.save(tmp.path().join("c.png")).unwrap();
        let d = image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::from_fn(w, h, |x, _| {
            image::Luma([5000 + 10 * x as u16])
        });
        d.save(tmp.path().join("d.png")).unwrap();
        let mut cam = PinholeCamera::new(30.0, 30.0, 15.5, 11.5, w, h);
        cam.distortion.k1 = 0.25;
        cam.distortion.p1 = -0.005;
        let f = load_pair_frame(
            &tmp.path().join("c.png"),
            &tmp.path().join("d.png"),
            &cam,
            5000.0,
        )
        .unwrap();
        let before = f.clone();
        let stored = f.colour.as_ref().unwrap();
        assert!(
            stored.fixed.get().is_none(),
            "nothing is undistorted before a read"
        );
        let want = remap_colour(
            &UndistortMap::new(&cam),
            &ColourImage::from_rgb(w as usize, h as usize, rgb.into_raw()).unwrap(),
        );
        assert_eq!(f.colour(), Some(&want));
        assert_ne!(
            want.rgb(),
            stored.stored.rgb(),
            "the camera's distortion moves pixels"
        );
        assert!(f.colour.as_ref().unwrap().fixed.get().is_some());
        let after = f.clone();
        assert!(after.colour.as_ref().unwrap().fixed.get().is_some());
        assert_eq!(after.colour(), Some(&want));
        assert_eq!(before.colour(), Some(&want));
    }

    #[test]
    fn association_is_one_to_one_and_closest_first() {
        let a = [0.0, 0.033, 0.066, 1.0];
        let b = [0.005, 0.030, 0.031, 0.2];
        let p = associate(&a, &b, 0.02);
        assert_eq!(p, vec![(0, 0), (1, 2)]);
        assert!(associate(&a, &b, 1e-4).is_empty());
        assert!((closest_difference(&a, &b).unwrap() - 0.002).abs() < 1e-12);
        assert_eq!(closest_difference(&a, &[]), None);
    }

    #[test]
    fn pose_line() {
        let p = parse_pose_line("1 2 3 0 0 0 2").unwrap();
        assert_eq!(p.translation, DVec3::new(1.0, 2.0, 3.0));
        assert!((p.rotation.w - 1.0).abs() < 1e-12);
        assert!(parse_pose_line("1 2 3 0 0 0")
            .unwrap_err()
            .contains("expected 7"));
        assert!(parse_pose_line("1 2 nan 0 0 0 1")
            .unwrap_err()
            .contains("not finite"));
    }

    #[test]
    fn depth_range_warning_names_the_factor_that_fits() {
        // Millimetre depth of a room (0.5-4 m) read with TUM's 5000: the median (0.45 m) is
        // plausible, but many depths fall below the sensor's range.
        let raw: Vec<u16> = (0..1000).map(|i| 500 + (i * 35 / 10) as u16).collect();
        assert!(check_depth_scale(&raw, 5000.0, Path::new("d.png")).is_ok());
        let w = depth_range_warning(&raw, 5000.0).expect("a warning");
        assert!(w.contains("factor 1000 would put 100 % inside"), "{w}");
        assert_eq!(depth_range_warning(&raw, 1000.0), None);
        // A room (1.8-4.4 m) in millimetres read with 5000: 0.36-0.88 m, a plausible close-up
        // but for the quarter under the sensor's 0.5 m.
        let room: Vec<u16> = (0..1000).map(|i| 1800 + (i * 26 / 10) as u16).collect();
        let w = depth_range_warning(&room, 5000.0).expect("a warning");
        assert!(w.contains("factor 1000 would put 100 % inside"), "{w}");
        assert_eq!(depth_range_warning(&room, 1000.0), None);
        // The reverse: TUM depth (5000 per metre) read as millimetres.
        let tum: Vec<u16> = raw.iter().map(|&d| d * 5).collect();
        let w = depth_range_warning(&tum, 1000.0).expect("a warning");
        assert!(w.contains("factor 5000"), "{w}");
    }

    #[test]
    fn depth_scale_check_suggests_a_factor() {
        let raw = vec![2000u16; 1000]; // 2 m at factor 1000
        assert!(check_depth_scale(&raw, 1000.0, Path::new("d.png")).is_ok());
        match check_depth_scale(&raw, 50000.0, Path::new("d.png")) {
            Err(IoError::DepthScaleMismatch { suggested, .. }) => {
                assert_eq!(suggested, Some(1000.0))
            }
            other => panic!("{other:?}"),
        }
    }
}
