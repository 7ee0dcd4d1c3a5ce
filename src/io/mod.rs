//! File formats: TUM RGB-D sequence folders, TUM trajectories, camera configuration files,
//! PLY point clouds ([`ply`]) and the run folder of a SLAM run ([`run_folder`]).
//!
//! Every reader reports malformed input as an [`IoError`] naming the file, the line (where
//! there is one) and the cause; nothing here panics on input.

pub mod config;
pub mod layouts;
mod opencv_yaml;
pub mod ply;
pub mod run_folder;
pub mod settings;
pub mod trajectory;
pub mod tum;
pub mod undistort;

pub use config::{CalibFormat, CameraConfig};
pub use layouts::Layout;
pub use tum::{
    load_pair_frame, parse_pose_line, read_intrinsic_matrix, read_pose_file, OpenOptions, RawFrame,
    RawPixels, SequenceEntry, TumSequence,
};
pub use undistort::UndistortMap;

use std::path::PathBuf;

/// Errors of the file readers and writers.
#[derive(Debug, thiserror::Error)]
pub enum IoError {
    /// The file could not be opened, read or written.
    #[error("{path}: {source}")]
    File {
        /// The file.
        path: PathBuf,
        /// The OS error.
        source: std::io::Error,
    },
    /// A line could not be parsed.
    #[error("{path}:{line}: {message}")]
    Parse {
        /// The file.
        path: PathBuf,
        /// 1-based line number.
        line: usize,
        /// What is wrong with it.
        message: String,
    },
    /// The file's content is malformed in a way that has no line (binary files, JSON
    /// structure, versions).
    #[error("{path}: {message}")]
    Malformed {
        /// The file.
        path: PathBuf,
        /// What is wrong with it.
        message: String,
    },
    /// The file parsed but holds no usable entries.
    #[error("{path}: {message}")]
    Empty {
        /// The file or folder.
        path: PathBuf,
        /// What was expected.
        message: String,
    },
    /// The sequence folder does not exist or is not a folder.
    #[error("{path}: sequence folder not found")]
    MissingFolder {
        /// The folder.
        path: PathBuf,
    },
    /// A file the reader needs is missing.
    #[error("{path}: missing {what}")]
    MissingFile {
        /// The file (or, when one of several would do, the first candidate).
        path: PathBuf,
        /// What the file is for.
        what: String,
    },
    /// An image file could not be decoded (corrupt, truncated, unsupported format).
    #[error("{path}: cannot decode image: {message}")]
    Image {
        /// The image file.
        path: PathBuf,
        /// The decoder's message.
        message: String,
    },
    /// Colour and depth images of one frame differ in size.
    #[error("colour {rgb} is {}x{} but depth {depth} is {}x{} pixels: they must match", rgb_size.0, rgb_size.1, depth_size.0, depth_size.1)]
    ImageSizeMismatch {
        /// The colour image.
        rgb: PathBuf,
        /// Its (width, height).
        rgb_size: (u32, u32),
        /// The depth image.
        depth: PathBuf,
        /// Its (width, height).
        depth_size: (u32, u32),
    },
    /// An image's size is not the camera's.
    #[error("{path}: image is {}x{} pixels but the camera ({camera_source}) is {}x{}", image_size.0, image_size.1, camera_size.0, camera_size.1)]
    CameraSizeMismatch {
        /// The image.
        path: PathBuf,
        /// Its (width, height).
        image_size: (u32, u32),
        /// The camera's (width, height).
        camera_size: (u32, u32),
        /// Where the camera came from.
        camera_source: String,
    },
    /// A depth image is not single-channel 16-bit.
    #[error("{path}: depth image must be single-channel 16-bit, found {found}")]
    DepthNot16Bit {
        /// The depth image.
        path: PathBuf,
        /// What it is instead.
        found: String,
    },
    /// The depth factor does not fit the data: the median valid depth is implausible.
    #[error("{path}: depth factor {factor} gives a median depth of {median_m:.4} m (plausible: 0.1-20 m); {}",
        match suggested { Some(s) => format!("factor {s} would fit (median {:.2} m)", median_m * factor / s), None => "no common factor fits".to_string() })]
    DepthScaleMismatch {
        /// The depth image.
        path: PathBuf,
        /// The depth factor in use (raw units per metre).
        factor: f64,
        /// The median valid depth it implies, metres.
        median_m: f64,
        /// A common factor (1, 10, 100, 1000, 5000, 10000) that gives a plausible median.
        suggested: Option<f64>,
    },
    /// No colour image has a depth image within the time tolerance.
    #[error("{path}: no colour/depth pairs within {max_difference} s of each other{}",
        match closest { Some(c) => format!(" (closest pair is {c:.6} s apart)"), None => String::new() })]
    NoAssociations {
        /// The sequence folder.
        path: PathBuf,
        /// The tolerance, seconds.
        max_difference: f64,
        /// The smallest time difference found, seconds.
        closest: Option<f64>,
    },
    /// A camera name is neither a preset nor an existing file.
    #[error("camera '{name}' is neither a preset ({presets}) nor an existing config file")]
    UnknownCamera {
        /// The name given.
        name: String,
        /// The known presets.
        presets: String,
    },
    /// Camera intrinsics are invalid.
    #[error("{path}: {source}")]
    InvalidCamera {
        /// The file (or preset) they came from.
        path: PathBuf,
        /// What is wrong.
        source: crate::camera::CameraError,
    },
    /// The depth factor is not finite and positive.
    #[error("{path}: depth factor {factor} must be finite and > 0")]
    InvalidDepthFactor {
        /// Where it came from.
        path: PathBuf,
        /// The value.
        factor: f64,
    },
    /// A depth image holds no measurement at all (every pixel 0): the frame cannot be
    /// tracked or fused.
    #[error("{path}: the depth image has no valid measurement (every pixel is 0)")]
    NoValidDepth {
        /// The depth image.
        path: PathBuf,
    },
    /// A decoded frame's buffers do not fit together.
    #[error("{path}: {source}")]
    Frame {
        /// The colour image of the frame.
        path: PathBuf,
        /// What did not fit.
        source: crate::image::ImageError,
    },
    /// Another run is writing this output folder.
    #[error("{path}: another rgbid run (process {pid}) is writing this folder; wait for it, or remove its lock file {} if no such run exists", path.join(run_folder::files::LOCK).display())]
    FolderLocked {
        /// The folder.
        path: PathBuf,
        /// The process holding the lock.
        pid: u32,
    },
    /// A frame index past the end of the sequence.
    #[error("frame {index} requested but the sequence has {len} frames")]
    IndexOutOfRange {
        /// The index asked for.
        index: usize,
        /// The number of frames.
        len: usize,
    },
}

impl IoError {
    /// Wraps an OS error with the path it concerns.
    pub fn file(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        IoError::File {
            path: path.into(),
            source,
        }
    }
    /// A parse error at `path:line`.
    pub fn parse(path: impl Into<PathBuf>, line: usize, message: impl Into<String>) -> Self {
        IoError::Parse {
            path: path.into(),
            line,
            message: message.into(),
        }
    }
}

/// Reads a text file whole, without a leading UTF-8 byte-order mark (editors on Windows write
/// one; left in, it would be an invisible part of the first token).
pub(crate) fn read_text(path: &std::path::Path) -> Result<String, IoError> {
    let text = std::fs::read_to_string(path).map_err(|e| IoError::file(path, e))?;
    Ok(match text.strip_prefix('\u{feff}') {
        Some(rest) => rest.to_string(),
        None => text,
    })
}

/// Writes a file atomically: `write` fills a temporary file in the same folder, which then
/// replaces `path` by a rename, so a reader (or a crash) sees the old file or the new one,
/// never half of one. Errors name `path`.
pub(crate) fn write_atomic(
    path: &std::path::Path,
    write: impl FnOnce(&mut std::io::BufWriter<&mut std::fs::File>) -> std::io::Result<()>,
) -> Result<(), IoError> {
    use std::io::Write;
    let io = |e| IoError::file(path, e);
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => std::path::Path::new("."),
    };
    let mut builder = tempfile::Builder::new();
    builder.prefix(".rgbid-tmp-");
    // A temporary file is private (0600); the output gets the permissions of the file it
    // replaces, or those of a newly created file (0644 before the umask) on Unix.
    let keep = std::fs::metadata(path).ok().map(|m| m.permissions());
    #[cfg(unix)]
    let keep = keep.or_else(|| {
        use std::os::unix::fs::PermissionsExt;
        Some(std::fs::Permissions::from_mode(0o644))
    });
    if let Some(p) = keep {
        builder.permissions(p);
    }
    let mut tmp = builder.tempfile_in(dir).map_err(io)?;
    {
        let mut w = std::io::BufWriter::new(tmp.as_file_mut());
        write(&mut w).map_err(io)?;
        w.flush().map_err(io)?;
    }
    tmp.as_file().sync_all().map_err(io)?;
    tmp.persist(path).map_err(|e| io(e.error))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Write;

    /// A full disk while a file is replaced (the OS error of `/dev/full`, where it exists, else
    /// the same kind made here) is an error naming the file, and the previous version stays
    /// whole, with no temporary file left beside it.
    #[test]
    fn a_full_disk_keeps_the_previous_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("trajectory.txt");
        write_atomic(&path, |w| w.write_all(b"1.0 0 0 0 0 0 0 1\n")).unwrap();
        let full = |w: &mut std::io::BufWriter<&mut std::fs::File>| -> std::io::Result<()> {
            w.write_all(&[b'x'; 100_000])?;
            match std::fs::OpenOptions::new().write(true).open("/dev/full") {
                Ok(mut f) => f.write_all(b"more").and(f.flush()),
                Err(_) => Err(std::io::Error::from(std::io::ErrorKind::StorageFull)),
            }
        };
        let e = write_atomic(&path, full).unwrap_err();
        match &e {
            IoError::File { path: p, source } => {
                assert_eq!(p, &path);
                assert_eq!(source.kind(), std::io::ErrorKind::StorageFull, "{e}");
            }
            other => panic!("{other:?}"),
        }
        assert!(e.to_string().contains("trajectory.txt"), "{e}");
        assert_eq!(
            std::fs::read_to_string(&path).unwrap(),
            "1.0 0 0 0 0 0 0 1\n"
        );
        let left: Vec<_> = std::fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        assert_eq!(left, vec![std::ffi::OsString::from("trajectory.txt")]);
    }
}
