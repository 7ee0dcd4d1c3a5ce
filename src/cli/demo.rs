//! `rgbid demo` (not implemented yet).

/// Arguments of `rgbid demo`.
#[derive(clap::Args)]
pub struct Args {}

/// Runs the subcommand.
pub fn run(_args: Args) -> anyhow::Result<()> {
    anyhow::bail!("`rgbid demo` is not implemented yet")
}
