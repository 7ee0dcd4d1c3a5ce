//! `rgbid synth` (not implemented yet).

/// Arguments of `rgbid synth`.
#[derive(clap::Args)]
pub struct Args {}

/// Runs the subcommand.
pub fn run(_args: Args) -> anyhow::Result<()> {
    anyhow::bail!("`rgbid synth` is not implemented yet")
}
