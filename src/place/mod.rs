//! Place recognition (thesis 6.4.4-6.4.5): ORB features, a bag of binary words, a keyframe
//! database with an inverted index, and geometric verification by 3-point RANSAC with Horn's
//! closed-form absolute orientation.
//!
//! Conventions: images are [`ImageF32`](crate::image::ImageF32) intensity in `[0, 255]`;
//! keypoint coordinates are level-0 pixels with integer coordinates at pixel centres; inverse
//! depth is 1/m with `0` meaning "no measurement"; 3D points are in the keyframe's camera frame
//! (x right, y down, z forward, metres); relative poses are named `a_from_b`.
//!
//! Pipeline: [`extract_orb`] -> [`Vocabulary::transform`] (BoW + direct index)
//! -> [`KeyframeDatabase::query`] -> [`match_descriptors`] -> [`verify_loop`].
//! [`LoopDetector`] strings these together for a stream of keyframes.

pub(crate) mod database;
pub(crate) mod detector;
pub(crate) mod matching;
pub(crate) mod orb;
pub(crate) mod pattern;
pub(crate) mod ransac;
pub(crate) mod verify;
pub(crate) mod vocabulary;

pub use database::{Candidate, KeyframeDatabase, QueryParams};
pub use detector::{DetectedLoop, KeyframeDescription, LoopDetector, LoopDetectorParams};
pub use matching::{
    hamming, match_descriptors, match_with_vocabulary, DescriptorMatch, MatchParams,
};
pub use orb::{extract_orb, Descriptor, KeyPoint, OrbFeatures, OrbParams};
pub use ransac::{horn_absolute_orientation, ransac_rigid, RansacParams, RansacResult};
pub use verify::{
    convex_hull_area, verify_loop, LoopMatch, PixelMatch, VerifyOutcome, VerifyParams,
};
pub use vocabulary::{BowVector, FeatureVector, Scoring, TrainParams, Vocabulary, Weighting};

use std::path::PathBuf;

/// Errors of the place-recognition module.
#[derive(Debug, thiserror::Error)]
pub enum PlaceError {
    /// An image, mask or inverse-depth map has a size that does not fit the others.
    #[error("size mismatch: {what} is {got_w}x{got_h}, expected {want_w}x{want_h}")]
    SizeMismatch {
        /// Which input.
        what: &'static str,
        /// Its width.
        got_w: usize,
        /// Its height.
        got_h: usize,
        /// Expected width.
        want_w: usize,
        /// Expected height.
        want_h: usize,
    },
    /// The image is too small for even one pyramid level with a descriptor border.
    #[error(
        "image {width}x{height} is too small for ORB (needs at least 2 x 19 + 1 pixels per side)"
    )]
    ImageTooSmall {
        /// Width in pixels.
        width: usize,
        /// Height in pixels.
        height: usize,
    },
    /// A parameter is out of its valid range.
    #[error("invalid parameter {name}: {why}")]
    InvalidParameter {
        /// Parameter name.
        name: &'static str,
        /// What is required.
        why: String,
    },
    /// Two point sets for absolute orientation have different lengths or too few points.
    #[error("point sets: {0}")]
    BadPointSets(String),
    /// The points are degenerate (collinear or coincident): no unique rotation.
    #[error("degenerate point configuration: {0}")]
    Degenerate(&'static str),
    /// Vocabulary training got no descriptors (or fewer than the branching factor).
    #[error("not enough training descriptors: {got} (need at least {need})")]
    NotEnoughTrainingData {
        /// Descriptors given.
        got: usize,
        /// Descriptors needed.
        need: usize,
    },
    /// A vocabulary file could not be read or written.
    #[error("{path}: {source}")]
    File {
        /// The file.
        path: PathBuf,
        /// The OS error.
        source: std::io::Error,
    },
    /// A vocabulary file is malformed (the message of the format's own error).
    #[error("{path}: {message}")]
    InFile {
        /// The file.
        path: PathBuf,
        /// What is wrong, with the byte offset (binary) or line (text).
        message: String,
    },
    /// A binary vocabulary file is malformed.
    #[error("malformed binary vocabulary: {0}")]
    BadBinaryVocabulary(String),
    /// A DBoW2 text vocabulary is malformed.
    #[error("malformed DBoW2 text vocabulary, line {line}: {message}")]
    BadTextVocabulary {
        /// 1-based line number.
        line: usize,
        /// What is wrong with it.
        message: String,
    },
    /// The vocabulary uses a scoring or weighting scheme this crate does not implement.
    #[error("unsupported vocabulary {what} code {code}")]
    Unsupported {
        /// `"scoring"` or `"weighting"`.
        what: &'static str,
        /// The DBoW2 enum value.
        code: u32,
    },
    /// A keyframe id is unknown to the database or detector.
    #[error("unknown keyframe {0}")]
    UnknownKeyframe(usize),
}
