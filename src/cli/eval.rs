//! `rgbid eval` (not implemented yet).

/// Arguments of `rgbid eval`.
#[derive(clap::Args)]
pub struct Args {}

/// Runs the subcommand.
pub fn run(_args: Args) -> anyhow::Result<()> {
    anyhow::bail!("`rgbid eval` is not implemented yet")
}
