//! Pose-graph and curve-graph optimisation (thesis ch. 7).
//!
//! - [`Problem`]: sparse non-linear least squares over manifold variables (LM / GN, robust
//!   kernels, faer sparse Cholesky with AMD ordering and a reused symbolic analysis).
//! - [`Se2`], [`Sim3`] and the [`Manifold`] trait (also for `Se3`, `DVec2`, `DVec3`).
//! - [`PoseGraph`]: SE(2)/SE(3)/Sim(3) pose graphs (eq. 7.1-7.6), chi2 and the SE-Sync
//!   objective.
//! - [`initialize_2d`], [`initialize_3d`]: spanning-tree, linear 2D and chordal 3D
//!   initialisation.
//! - [`g2o`], [`isam`]: the g2o and iSAM text formats (read and write).
//!
//! Vertices are `world_from_body` transforms, edges `from_from_to` measurements with an
//! information matrix ordered like the residual (translation first). Metres and radians.

pub mod curve;
pub mod eval;
pub mod g2o;
pub mod incremental;
pub(crate) mod init;
pub mod isam;
pub(crate) mod lie;
pub mod planar;
pub(crate) mod pose_graph;
pub(crate) mod solver;

pub use init::{initialize_2d, initialize_3d, InitMethod};
pub use lie::{Manifold, Se2, Sim3};
pub use pose_graph::{Edge, EdgeCost, Pose, PoseGraph, PoseGraph2, PoseGraph3, PoseGraphSim3};
pub use solver::{
    Algorithm, Factor, Problem, RobustKernel, SolveReport, SolverOptions, Termination,
};

/// Errors of graph construction and optimisation.
#[derive(Debug, thiserror::Error)]
pub enum GraphError {
    /// Two vertices with the same id.
    #[error("duplicate vertex id {0}")]
    DuplicateVertex(i64),
    /// An edge refers to a vertex that does not exist.
    #[error("unknown vertex id {0}")]
    UnknownVertex(i64),
    /// A vertex cannot be reached from the gauge (fixed) vertices through edges.
    #[error("graph is not connected: vertex {vertex} is not linked to the fixed vertex")]
    Disconnected {
        /// Id of a vertex outside the gauge's component.
        vertex: i64,
    },
    /// An information matrix that is not symmetric positive definite.
    #[error("information matrix of edge {from}-{to} is not symmetric positive definite")]
    InformationNotPositiveDefinite {
        /// First vertex id.
        from: i64,
        /// Second vertex id.
        to: i64,
    },
    /// NaN or infinite input or intermediate values.
    #[error("non-finite value: {0}")]
    NonFinite(String),
    /// The normal equations are singular (Gauss-Newton without damping).
    #[error("singular normal equations")]
    SingularSystem,
    /// The sparse linear algebra failed.
    #[error("sparse linear algebra: {0}")]
    Linear(String),
    /// A degenerate curve-graph configuration (e.g. coincident consecutive positions).
    #[error("degenerate curve segment: {0}")]
    DegenerateSegment(String),
    /// Other invalid input.
    #[error("invalid graph: {0}")]
    Invalid(String),
}
