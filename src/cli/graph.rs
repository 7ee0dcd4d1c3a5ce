//! `rgbid graph` (not implemented yet).

/// Subcommands of `rgbid graph`.
#[derive(clap::Subcommand)]
pub enum Command {
    /// Not implemented yet.
    Todo,
}

/// Runs the subcommand.
pub fn run(_c: Command) -> anyhow::Result<()> {
    anyhow::bail!("`rgbid graph` is not implemented yet")
}
