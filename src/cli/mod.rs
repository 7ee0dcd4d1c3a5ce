//! Subcommand implementations of the `rgbid` binary (one file each).

mod ahead;
pub mod bench;
pub mod config;
pub mod demo;
pub mod eval;
pub mod export;
pub mod graph;
pub mod heap;
pub mod load;
pub mod mesh;
pub mod mono;
pub mod odometry;
pub mod options;
pub mod outcome;
pub mod outputs;
pub mod place;
pub mod plot;
pub mod report;
pub mod rerun;
pub mod scale;
pub mod segment;
pub mod slam;
pub mod synth;
pub mod vocab;
