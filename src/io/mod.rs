//! File formats: TUM RGB-D sequence folders, TUM trajectories, camera configuration files,
//! and (as they land) g2o / iSAM pose graphs and PLY point clouds.
//!
//! Every reader reports malformed input as an [`IoError`] naming the file, the line (where
//! there is one) and the cause; nothing here panics on input.

pub mod trajectory;
pub mod tum_writer;

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
    /// The file parsed but holds no usable entries.
    #[error("{path}: {message}")]
    Empty {
        /// The file or folder.
        path: PathBuf,
        /// What was expected.
        message: String,
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
