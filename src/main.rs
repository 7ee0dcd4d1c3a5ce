//! The `rgbid` command-line interface: one subcommand per job.
// `!(x > 0.0)` is used on purpose: it also rejects NaN.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

use anyhow::Result;
use clap::{Parser, Subcommand};

mod cli;

/// rgbid: dense RGB-D odometry with inverse depth, and the rest of the thesis' SLAM systems,
/// on any GPU (or the CPU).
#[derive(Parser)]
#[command(name = "rgbid", version, about, long_about = None, after_help = cli::outcome::EXIT_CODES_HELP)]
struct Cli {
    /// Log level (error, warn, info, debug, trace); RUST_LOG overrides it.
    #[arg(long, global = true, default_value = "info")]
    log: String,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Render a synthetic sequence, run odometry on it and report accuracy against its exact
    /// ground truth (no downloads needed).
    Demo(cli::demo::Args),
    /// Dense RGB-D odometry over a TUM-layout sequence folder; writes a TUM trajectory.
    Odometry(cli::odometry::Args),
    /// ATE and RPE of an estimated trajectory against ground truth (TUM definitions).
    Eval(cli::eval::Args),
    /// Speed benchmarks that print per-frame and per-stage medians.
    #[command(subcommand)]
    Bench(cli::bench::Command),
    /// Render synthetic RGB-D / omnidirectional sequences with exact ground truth.
    Synth(cli::synth::Args),
    /// Place recognition: loop detection over a sequence, ORB benchmark.
    #[command(subcommand)]
    Place(cli::place::Command),
    /// Bag-of-binary-words vocabularies: train, inspect, convert.
    #[command(subcommand)]
    Vocab(cli::vocab::Command),
    /// Superjut segmentation: segment images, neg-entropy images, masks and a feature CSV.
    Segment(cli::segment::Args),
    /// Dense TSDF reconstruction: integrates every frame of a TUM sequence at the poses of a
    /// trajectory and writes a coloured mesh (PLY).
    Mesh(cli::mesh::Args),
    /// Pose-graph and curve-graph optimisation.
    #[command(subcommand)]
    Graph(cli::graph::Command),
    /// A run folder's or map's trajectory (TUM, KITTI, EuRoC), model (PLY, OBJ) or keyframe
    /// pose graph (g2o) in the format another tool reads.
    Export(cli::export::Args),
    /// RGB-ID SLAM: tracking, keyframe fusion, loop closure, pose graph, maps across
    /// sessions; writes trajectories, loops, a PLY model and timings.
    Slam(cli::slam::Args),
    /// True metric scale of a walking person's monocular trajectory (step frequency).
    Scale(cli::scale::Args),
    /// Monocular EKF SLAM for pinhole, fisheye and catadioptric cameras (unified model).
    Mono(Box<cli::mono::Args>),
    /// Configurations as data: `rgbid config dump --command slam` prints the defaults as
    /// TOML (a starting point for `--config`).
    #[command(subcommand)]
    Config(cli::config::Command),
    /// List the GPU adapters wgpu can see.
    Adapters,
}

fn main() {
    let cli = Cli::parse();
    if std::env::var_os("XDG_RUNTIME_DIR").is_none() {
        // Mesa's Vulkan drivers complain on every adapter query when this is unset (headless
        // servers); a private temporary directory is what they need.
        std::env::set_var("XDG_RUNTIME_DIR", std::env::temp_dir());
    }
    env_logger::Builder::from_env(env_logger::Env::default().default_filter_or(&cli.log))
        .format_timestamp(None)
        .init();
    if let Err(e) = run(cli.command) {
        let code = cli::outcome::exit_code(&e);
        let label = if code == cli::outcome::ERROR {
            "error: "
        } else {
            ""
        };
        eprintln!("{label}{}", cli::outcome::message(&e));
        std::process::exit(code);
    }
}

fn run(command: Command) -> Result<()> {
    match command {
        Command::Demo(a) => cli::demo::run(a),
        Command::Mesh(a) => cli::mesh::run(a),
        Command::Odometry(a) => cli::odometry::run(a),
        Command::Eval(a) => cli::eval::run(a),
        Command::Bench(c) => cli::bench::run(c),
        Command::Synth(a) => cli::synth::run(a),
        Command::Place(c) => cli::place::run(c),
        Command::Vocab(c) => cli::vocab::run(c),
        Command::Segment(a) => cli::segment::run(a),
        Command::Graph(c) => cli::graph::run(c),
        Command::Export(a) => cli::export::run(a),
        Command::Slam(a) => cli::slam::run(a),
        Command::Scale(a) => cli::scale::run(a),
        Command::Mono(a) => cli::mono::run(*a),
        Command::Config(c) => cli::config::run(c),
        Command::Adapters => {
            let list = rgbid::gpu::describe_adapters();
            if list.is_empty() {
                println!("no adapters (install mesa-vulkan-drivers for lavapipe)");
            }
            for l in list {
                println!("{l}");
            }
            Ok(())
        }
    }
}
