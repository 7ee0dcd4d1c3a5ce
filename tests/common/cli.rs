//! Running the `rgbid` binary from the tests that need the `cli` feature.

use std::process::{Command, Output};

/// Runs `rgbid ARGS` with warnings-only logging.
pub fn rgbid(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_rgbid"))
        .args(args)
        .env("RUST_LOG", "warn")
        .output()
        .expect("running rgbid")
}

/// Standard output and error of a run, for assertion messages.
pub fn text(o: &Output) -> String {
    format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    )
}
