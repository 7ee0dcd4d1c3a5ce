//! The thesis' experiment harnesses: generated data with exact ground truth, run through the
//! systems and scored as the thesis' tables and figures do. Behind the `experiments` feature
//! (enabled by the `cli` feature), so a library user who only embeds the systems does not
//! build them.
//!
//! - [`segment`]: the changed-environment experiments of chapter 5 (ROC AUC per superjut
//!   feature, masked matching across generated sessions).
//! - [`mesh_change`]: the mesh experiment of chapter 5 (TSDF meshes of changed sessions,
//!   eq. 5.3 ground truth, changed-area detection and masked matching per neg-entropy
//!   threshold).
//! - [`scale`]: tables 3.1-3.4 analogues (walking scale on emulated drift or on the monocular
//!   EKF of rendered catadioptric walks).
//! - [`mono`]: monocular EKF SLAM on rendered sequences with ground truth (table 2.1).
//! - [`patches`]: the decoupled matching experiment of sec. 2.6.1 (plain against warped
//!   patches under rotation, translation and scale sweeps).
//! - [`graph`]: the pose-graph suite of chapter 7 (data sets, the tilted-plane experiment).
//! - [`peers`]: the peer implementations (OpenCV, Open3D, GTSAM) run through their Python
//!   scripts, for the benchmarks.

pub mod graph;
pub mod mesh_change;
pub mod mono;
pub mod patches;
pub mod peers;
pub mod scale;
pub mod segment;
