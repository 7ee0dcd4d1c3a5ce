//! Writes rendered pinhole sequences in any [`Layout`] that [`crate::io::tum::TumSequence`]
//! reads, as each dataset documents its files (the reader's table in [`crate::io::layouts`]):
//!
//! | layout | written |
//! |---|---|
//! | TUM (also ICL-NUIM's TUM variant) | [`TumWriter`]'s folder |
//! | ETH3D | `rgb/<t>.png`, `depth/<t>.png` (5000 per metre), `rgb.txt`, `depth.txt`, `calibration.txt` (`fx fy cx cy`), `groundtruth.txt` (TUM lines) |
//! | 7-Scenes | `frame-NNNNNN.color.png`, `frame-NNNNNN.depth.png` (millimetres, 65535 = none), `frame-NNNNNN.pose.txt` (4x4 camera-to-world) |
//! | ScanNet | `color/N.jpg` at [`SCANNET_COLOUR_SCALE`] times the depth size (upsampled, its own intrinsics), `depth/N.png` (millimetres, 0 = none), `pose/N.txt`, `intrinsic/intrinsic_{color,depth}.txt` (4x4) |
//! | Replica (NICE-SLAM) | `results/frameNNNNNN.jpg`, `results/depthNNNNNN.png` (6553.5 per metre, 0 = none), `traj.txt` (one row-major 4x4 camera-to-world per line) |
//!
//! 7-Scenes and Replica carry no camera of the rendered size in their files (their readers
//! use the datasets' presets), so those folders also get `calib.txt` in DROID-SLAM's form
//! (`fx fy cx cy`), read with `--camera DIR/calib.txt --calib-format droid`. Layouts without
//! time stamps are written at the sequence's frame rate from t = 0, which is how their readers
//! time-stamp them at that rate. Colour JPEGs are written at quality 95.

use std::fmt::Write as _;
use std::io::Write as _;
use std::path::{Path, PathBuf};

use image::codecs::jpeg::JpegEncoder;
use image::codecs::png::PngEncoder;
use image::{ImageBuffer, Luma, RgbImage};

use super::tum_export::TumWriter;
use super::{CameraModel, RenderedFrame};
use crate::camera::PinholeCamera;
use crate::geometry::Se3;
use crate::io::trajectory::write_tum;
use crate::io::{IoError, Layout};
use crate::trajectory::TimedPose;

/// ScanNet colour images are written this many times wider and taller than the depth images
/// (the dataset's own colour camera is about twice its depth camera's size).
pub const SCANNET_COLOUR_SCALE: u32 = 2;

/// JPEG quality of the colour images of ScanNet and Replica (0-100).
const JPEG_QUALITY: u8 = 95;

/// Writes one folder in a [`Layout`], frame by frame.
pub struct LayoutWriter {
    layout: Layout,
    dir: PathBuf,
    camera: PinholeCamera,
    tum: Option<TumWriter>,
    poses: Vec<TimedPose>,
    rgb_list: String,
    depth_list: String,
    traj: String,
}

fn write_text(path: &Path, text: &str) -> Result<(), IoError> {
    let mut f = std::fs::File::create(path).map_err(|e| IoError::file(path, e))?;
    f.write_all(text.as_bytes())
        .map_err(|e| IoError::file(path, e))
}

fn create_dir(p: &Path) -> Result<(), IoError> {
    std::fs::create_dir_all(p).map_err(|e| IoError::file(p, e))
}

/// The 16 numbers of a row-major 4x4 matrix of `pose`, separated by `sep` within a row and
/// `row_sep` between rows.
fn matrix_text(pose: &Se3, sep: &str, row_sep: &str) -> String {
    let m = pose.to_mat4();
    (0..4)
        .map(|r| {
            let row = m.row(r);
            [row.x, row.y, row.z, row.w]
                .iter()
                .map(|v| format!("{v:.9e}"))
                .collect::<Vec<_>>()
                .join(sep)
        })
        .collect::<Vec<_>>()
        .join(row_sep)
}

/// A 4x4 intrinsic matrix as the ScanNet exporter writes it.
fn intrinsic_text(c: &PinholeCamera) -> String {
    format!(
        "{} 0 {} 0\n0 {} {} 0\n0 0 1 0\n0 0 0 1\n",
        c.fx, c.cx, c.fy, c.cy
    )
}

fn save(
    path: &Path,
    f: impl FnOnce(&mut std::io::BufWriter<std::fs::File>) -> image::ImageResult<()>,
) -> Result<(), IoError> {
    let file = std::fs::File::create(path).map_err(|e| IoError::file(path, e))?;
    let mut w = std::io::BufWriter::new(file);
    f(&mut w).map_err(|e| IoError::file(path, std::io::Error::other(e)))?;
    w.flush().map_err(|e| IoError::file(path, e))
}

fn save_png_rgb(path: &Path, img: &RgbImage) -> Result<(), IoError> {
    save(path, |w| img.write_with_encoder(PngEncoder::new(w)))
}

fn save_jpg(path: &Path, img: &RgbImage) -> Result<(), IoError> {
    save(path, |w| {
        img.write_with_encoder(JpegEncoder::new_with_quality(w, JPEG_QUALITY))
    })
}

fn save_depth(path: &Path, w: u32, h: u32, raw: Vec<u16>) -> Result<(), IoError> {
    let img: ImageBuffer<Luma<u16>, Vec<u16>> =
        ImageBuffer::from_raw(w, h, raw).ok_or_else(|| IoError::Empty {
            path: path.into(),
            message: "depth buffer size does not match".into(),
        })?;
    save(path, |f| img.write_with_encoder(PngEncoder::new(f)))
}

/// Depth of `frame` as 16-bit values at `factor` units per metre; pixels without a
/// measurement, and depths past the 16-bit range, become `none`.
fn raw_depth(frame: &RenderedFrame, factor: f64, none: u16) -> Vec<u16> {
    frame
        .inverse_depth
        .data
        .iter()
        .map(|&rho| {
            let v = (factor / f64::from(rho)).round();
            if rho > 0.0 && v >= 1.0 && v < f64::from(u16::MAX) {
                v as u16
            } else {
                none
            }
        })
        .collect()
}

impl LayoutWriter {
    /// Creates `dir` and the layout's folders, and writes its camera files for `camera` (the
    /// camera the frames are rendered with; distortion is not written, so it must have none).
    pub fn create(dir: &Path, layout: Layout, camera: &PinholeCamera) -> Result<Self, IoError> {
        if !camera.distortion.is_zero() {
            return Err(IoError::Malformed {
                path: dir.into(),
                message: "the layouts are written for undistorted cameras only".into(),
            });
        }
        create_dir(dir)?;
        let droid = || {
            write_text(
                &dir.join("calib.txt"),
                &format!("{} {} {} {}\n", camera.fx, camera.fy, camera.cx, camera.cy),
            )
        };
        let mut tum = None;
        match layout {
            Layout::Tum => tum = Some(TumWriter::create(dir, &CameraModel::Pinhole(*camera))?),
            Layout::Eth3d => {
                create_dir(&dir.join("rgb"))?;
                create_dir(&dir.join("depth"))?;
                write_text(
                    &dir.join("calibration.txt"),
                    &format!("{} {} {} {}\n", camera.fx, camera.fy, camera.cx, camera.cy),
                )?;
            }
            Layout::SevenScenes => droid()?,
            Layout::ScanNet => {
                for sub in ["color", "depth", "pose", "intrinsic"] {
                    create_dir(&dir.join(sub))?;
                }
                write_text(
                    &dir.join("intrinsic").join("intrinsic_depth.txt"),
                    &intrinsic_text(camera),
                )?;
                write_text(
                    &dir.join("intrinsic").join("intrinsic_color.txt"),
                    &intrinsic_text(&scannet_colour_camera(camera)),
                )?;
            }
            Layout::Replica => {
                create_dir(&dir.join("results"))?;
                droid()?;
            }
        }
        Ok(LayoutWriter {
            layout,
            dir: dir.into(),
            camera: *camera,
            tum,
            poses: Vec::new(),
            rgb_list: "# color images\n# timestamp filename\n".into(),
            depth_list: "# depth maps (16-bit, 5000 per metre)\n# timestamp filename\n".into(),
            traj: String::new(),
        })
    }

    /// The output folder.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Writes frame `self.frames()` (numbered from 0 in the order written) with its time stamp
    /// (seconds) and ground-truth pose.
    pub fn write_frame(
        &mut self,
        timestamp: f64,
        world_from_camera: &Se3,
        frame: &RenderedFrame,
    ) -> Result<(), IoError> {
        let (w, h) = (frame.width() as u32, frame.height() as u32);
        if (w, h) != (self.camera.width, self.camera.height) {
            return Err(IoError::Malformed {
                path: self.dir.clone(),
                message: format!(
                    "frame of {w} x {h} pixels for a {} x {} camera",
                    self.camera.width, self.camera.height
                ),
            });
        }
        if let Some(t) = &mut self.tum {
            return t.write_frame(timestamp, world_from_camera, frame);
        }
        let i = self.poses.len();
        let rgb = RgbImage::from_raw(w, h, frame.rgb.clone()).ok_or_else(|| IoError::Empty {
            path: self.dir.clone(),
            message: "rgb buffer size does not match".into(),
        })?;
        let d = &self.dir;
        match self.layout {
            Layout::Tum => {}
            Layout::Eth3d => {
                let name = format!("{timestamp:.6}.png");
                save_png_rgb(&d.join("rgb").join(&name), &rgb)?;
                save_depth(
                    &d.join("depth").join(&name),
                    w,
                    h,
                    raw_depth(frame, 5000.0, 0),
                )?;
                let _ = writeln!(self.rgb_list, "{timestamp:.6} rgb/{name}");
                let _ = writeln!(self.depth_list, "{timestamp:.6} depth/{name}");
            }
            Layout::SevenScenes => {
                let stem = format!("frame-{i:06}");
                save_png_rgb(&d.join(format!("{stem}.color.png")), &rgb)?;
                save_depth(
                    &d.join(format!("{stem}.depth.png")),
                    w,
                    h,
                    raw_depth(frame, 1000.0, u16::MAX),
                )?;
                write_text(
                    &d.join(format!("{stem}.pose.txt")),
                    &(matrix_text(world_from_camera, "\t", "\n") + "\n"),
                )?;
            }
            Layout::ScanNet => {
                let s = SCANNET_COLOUR_SCALE;
                let big = image::imageops::resize(
                    &rgb,
                    w * s,
                    h * s,
                    image::imageops::FilterType::Triangle,
                );
                save_jpg(&d.join("color").join(format!("{i}.jpg")), &big)?;
                save_depth(
                    &d.join("depth").join(format!("{i}.png")),
                    w,
                    h,
                    raw_depth(frame, 1000.0, 0),
                )?;
                write_text(
                    &d.join("pose").join(format!("{i}.txt")),
                    &(matrix_text(world_from_camera, " ", "\n") + "\n"),
                )?;
            }
            Layout::Replica => {
                let r = d.join("results");
                save_jpg(&r.join(format!("frame{i:06}.jpg")), &rgb)?;
                save_depth(
                    &r.join(format!("depth{i:06}.png")),
                    w,
                    h,
                    raw_depth(frame, 6553.5, 0),
                )?;
                let _ = writeln!(self.traj, "{}", matrix_text(world_from_camera, " ", " "));
            }
        }
        self.poses.push(TimedPose {
            timestamp,
            world_from_camera: *world_from_camera,
        });
        Ok(())
    }

    /// Writes the lists and ground-truth files, an extra text file per `(name, text)` pair,
    /// and `README.txt`.
    pub fn finish(self, readme: &str, extra: &[(&str, String)]) -> Result<(), IoError> {
        if let Some(t) = self.tum {
            return t.finish(readme, extra);
        }
        let d = &self.dir;
        match self.layout {
            Layout::Eth3d => {
                write_text(&d.join("rgb.txt"), &self.rgb_list)?;
                write_text(&d.join("depth.txt"), &self.depth_list)?;
                write_tum(&d.join("groundtruth.txt"), &self.poses)?;
            }
            Layout::Replica => write_text(&d.join("traj.txt"), &self.traj)?,
            Layout::Tum | Layout::SevenScenes | Layout::ScanNet => {}
        }
        for (name, text) in extra {
            write_text(&d.join(name), text)?;
        }
        write_text(&d.join("README.txt"), readme)
    }
}

/// The ScanNet colour camera [`LayoutWriter`] writes for a depth camera: the same field of
/// view at [`SCANNET_COLOUR_SCALE`] times the size (pixel centres at integers).
pub fn scannet_colour_camera(depth: &PinholeCamera) -> PinholeCamera {
    let s = f64::from(SCANNET_COLOUR_SCALE);
    PinholeCamera::new(
        depth.fx * s,
        depth.fy * s,
        (depth.cx + 0.5) * s - 0.5,
        (depth.cy + 0.5) * s - 0.5,
        depth.width * SCANNET_COLOUR_SCALE,
        depth.height * SCANNET_COLOUR_SCALE,
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn matrices_are_row_major() {
        let pose = Se3::new(glam::DQuat::IDENTITY, glam::DVec3::new(1.0, 2.0, 3.0));
        let t = matrix_text(&pose, " ", " ");
        let v: Vec<f64> = t.split(' ').map(|x| x.parse().unwrap()).collect();
        assert_eq!(
            v,
            [1.0, 0.0, 0.0, 1.0, 0.0, 1.0, 0.0, 2.0, 0.0, 0.0, 1.0, 3.0, 0.0, 0.0, 0.0, 1.0]
        );
    }
}
