//! The `rgbid` command-line interface: one subcommand per job.
// `!(x > 0.0)` is used on purpose: it also rejects NaN.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

use anyhow::Result;
use clap::{Parser, Subcommand};

mod cli;

/// Counts live heap bytes for `rgbid bench load` (see `cli::heap`).
#[global_allocator]
static HEAP: cli::heap::Counting = cli::heap::Counting;

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
    /// trajectory (into a new volume, or a saved one with --volume) and writes a coloured
    /// mesh (PLY); --save-volume keeps the volume.
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
    cli::heap::keep_freed_buffers();
    cli::heap::init_trace_from_env();
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

#[cfg(test)]
mod tests {
    use super::*;
    use clap::CommandFactory;
    use std::any::TypeId;

    /// What a message or a help text says to state a valid range.
    const RANGE_WORDS: [&str; 9] = [
        ">= ", "> 0", " to ", "[0, 1]", "(0, ", "(-1, 1)", "finite", "[0.001", "at least",
    ];

    fn states_a_range(text: &str) -> bool {
        RANGE_WORDS.iter().any(|w| text.contains(w))
    }

    /// Every option of every subcommand, with the subcommand path that reaches it.
    fn options(cmd: &clap::Command, path: &[String], out: &mut Vec<(Vec<String>, clap::Arg)>) {
        for a in cmd.get_arguments() {
            out.push((path.to_vec(), a.clone()));
        }
        for sub in cmd.get_subcommands() {
            let mut p = path.to_vec();
            p.push(sub.get_name().to_string());
            options(sub, &p, out);
        }
    }

    /// Every numeric option of every subcommand rejects a value that is no number, and each
    /// of NaN, -1 and 1e400 that it rejects, with a usage error that names the option and
    /// states the valid range; its --help text states the range too.
    #[test]
    fn every_numeric_option_is_range_checked_with_a_message_naming_it() {
        let numeric = [
            TypeId::of::<f64>(),
            TypeId::of::<f32>(),
            TypeId::of::<usize>(),
            TypeId::of::<u64>(),
            TypeId::of::<u32>(),
            TypeId::of::<u16>(),
            TypeId::of::<u8>(),
            TypeId::of::<i64>(),
            TypeId::of::<i32>(),
        ];
        let mut all = Vec::new();
        options(&Cli::command(), &[], &mut all);
        let mut checked = 0;
        let mut problems = Vec::new();
        for (path, arg) in &all {
            let ty = arg.get_value_parser().type_id();
            let Some(long) = arg.get_long() else { continue };
            if !numeric.iter().any(|t| ty == *t) {
                continue;
            }
            checked += 1;
            let name = format!("{} --{long}", path.join(" "));
            let help = arg
                .get_long_help()
                .or(arg.get_help())
                .map(|h| h.to_string())
                .unwrap_or_default();
            if !states_a_range(&help) {
                problems.push(format!("{name}: --help states no range: {help}"));
            }
            for (k, bad) in ["x", "nan", "-1", "1e400"].into_iter().enumerate() {
                let mut argv = vec!["rgbid".to_string()];
                argv.extend(path.iter().cloned());
                argv.push(format!("--{long}={bad}"));
                match Cli::try_parse_from(&argv) {
                    Err(e) if e.kind() == clap::error::ErrorKind::ValueValidation => {
                        let m = e.to_string();
                        if !m.contains(&format!("--{long}")) || !states_a_range(&m) {
                            problems.push(format!("{name}={bad}: {m}"));
                        }
                        assert_eq!(e.exit_code(), 2, "{name}");
                    }
                    // Values in the range are accepted; a number that is no number is not.
                    Ok(_) | Err(_) if k > 0 => {}
                    other => problems.push(format!("{name}={bad}: {:?}", other.err())),
                }
            }
        }
        assert!(checked > 80, "{checked} numeric options");
        assert!(problems.is_empty(), "{}", problems.join("\n"));
    }
}
