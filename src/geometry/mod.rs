//! Rigid-body geometry on `glam` f64 types: SO(3) and SE(3) exponential and logarithm maps,
//! the `Se3` transform type, and small helpers.
//!
//! Conventions: a transform is named by the frames it maps between, `a_from_b`, so that
//! `p_a = a_from_b * p_b`. Twists are ordered `[v; w]` (translation first, then rotation), in
//! metres and radians. Perturbations are applied on the left: `exp(xi) * a_from_b`.

mod se3;
mod so3;

pub use se3::Se3;
pub use so3::{skew, so3_exp, so3_log};
