// Shared declarations of the rgbid kernels. Constants mirror src/odometry/kernel.rs and
// src/odometry/robust.rs; a unit test checks that they agree.
const HUBER_K: f32 = 1.345;
const TUKEY_C: f32 = 4.685;
const INVALID_GRAD: f32 = 1e30;
const INVALID_RESIDUAL: f32 = 3e38;
const MIN_DEPTH: f32 = 0.05;
const MAX_REL_GRAD: f32 = 0.05;
