//! `rgbid bench` (not implemented yet).

/// Subcommands of `rgbid bench`.
#[derive(clap::Subcommand)]
pub enum Command {
    /// Not implemented yet.
    Todo,
}

/// Runs the subcommand.
pub fn run(_c: Command) -> anyhow::Result<()> {
    anyhow::bail!("`rgbid bench` is not implemented yet")
}
