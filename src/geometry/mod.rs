//! Rigid-body geometry on `glam` f64 types: SO(3) and SE(3) exponential and logarithm maps,
//! the `Se3` transform type, and small helpers.
//!
//! Conventions: a transform is named by the frames it maps between, `a_from_b`, so that
//! `p_a = a_from_b * p_b`. Twists are ordered `[v; w]` (translation first, then rotation), in
//! metres and radians.
//!
//! Perturbation convention (the one used by every covariance and every pose-graph increment in
//! the library): on the right, in the frame the transform maps from,
//! `a_from_b <- a_from_b * exp(d)` with `d = [v; w]` expressed in frame `b`. A covariance of
//! `a_from_b` is the covariance of that `d`. Moving it to another frame is an adjoint:
//! `a_from_b * exp(d) * b_from_c = a_from_c * exp(Ad(c_from_b) d)`.

mod covariance;
mod se3;
mod so3;

pub use covariance::Covariance6;
pub use se3::Se3;
pub use so3::{skew, so3_exp, so3_log};
