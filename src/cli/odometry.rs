//! `rgbid odometry` (not implemented yet).

/// Arguments of `rgbid odometry`.
#[derive(clap::Args)]
pub struct Args {}

/// Runs the subcommand.
pub fn run(_args: Args) -> anyhow::Result<()> {
    anyhow::bail!("`rgbid odometry` is not implemented yet")
}
