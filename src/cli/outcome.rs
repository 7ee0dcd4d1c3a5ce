//! How a command ends: the exit codes shared by every command, the two non-error endings that
//! travel as errors (finished with warnings, interrupted), and the error message printed.

use std::fmt;
use std::path::PathBuf;

// Exit codes 0 (success) and 2 (usage: clap's own code for a bad command line) need no
// constant here: `main` returns normally, and clap exits by itself.
/// Exit code: an error stopped the command.
pub const ERROR: i32 = 1;
/// Exit code: finished, outputs complete, with warnings.
pub const WARNINGS: i32 = 3;
/// Exit code: stopped by SIGINT/SIGTERM (128 + SIGINT, the shell convention).
pub const INTERRUPTED: i32 = 130;

/// The exit codes, for `rgbid --help`.
pub const EXIT_CODES_HELP: &str = "Exit codes (every command): 0 success; 1 error; 2 usage \
(a bad option or value); 3 finished with warnings, outputs complete (not converged, no \
evaluation possible, frames skipped); 130 interrupted (SIGINT/SIGTERM), partial outputs \
written.";

/// The command finished and its outputs are complete, but something deserves attention
/// (exit code 3).
#[derive(Debug)]
pub struct Warnings(pub Vec<String>);

impl fmt::Display for Warnings {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "finished with warnings: {}", self.0.join("; "))
    }
}

impl std::error::Error for Warnings {}

/// Returns `Ok(())` without warnings, else the [`Warnings`] error (exit code 3).
pub fn warnings(list: Vec<String>) -> anyhow::Result<()> {
    if list.is_empty() {
        Ok(())
    } else {
        Err(Warnings(list).into())
    }
}

/// The command was stopped by a signal after writing its partial outputs to `out`
/// (exit code 130).
#[derive(Debug)]
pub struct Interrupted {
    /// Where the partial outputs are (`None`: the command was given nowhere to write them).
    pub out: Option<PathBuf>,
}

impl fmt::Display for Interrupted {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match &self.out {
            Some(out) => write!(
                f,
                "interrupted; the outputs up to the interruption are in {}",
                out.display()
            ),
            None => write!(f, "interrupted; no output was asked for"),
        }
    }
}

impl std::error::Error for Interrupted {}

/// The exit code for a command's error.
pub fn exit_code(e: &anyhow::Error) -> i32 {
    if e.downcast_ref::<Warnings>().is_some() {
        WARNINGS
    } else if e.downcast_ref::<Interrupted>().is_some() {
        INTERRUPTED
    } else {
        ERROR
    }
}

/// Longest token echoed whole in a message; longer ones are cut in the middle.
const MAX_TOKEN_CHARS: usize = 80;

/// A token of a message as printed: a byte-order mark made visible, long tokens cut.
fn readable_token(token: &str) -> String {
    let token = token.replace('\u{feff}', "<U+FEFF byte-order mark>");
    let chars = token.chars().count();
    if chars <= MAX_TOKEN_CHARS {
        return token;
    }
    let head: String = token.chars().take(MAX_TOKEN_CHARS / 2).collect();
    let tail: String = token.chars().skip(chars - 16).collect();
    format!("{head}...{tail} ({} bytes)", token.len())
}

/// One line of text with every long token shortened.
fn readable(text: &str) -> String {
    let mut out = String::with_capacity(text.len().min(4096));
    let mut token = String::new();
    for c in text.chars() {
        if c.is_whitespace() {
            out.push_str(&readable_token(&token));
            token.clear();
            out.push(c);
        } else {
            token.push(c);
        }
    }
    out.push_str(&readable_token(&token));
    out
}

/// The error chain as one line, outermost first: a cause whose text the message already
/// holds (an OS error that both a wrapper and its source print) is left out, long tokens are
/// cut, a byte-order mark is named.
pub fn message(e: &anyhow::Error) -> String {
    let mut parts: Vec<String> = Vec::new();
    for cause in e.chain() {
        let text = readable(&cause.to_string());
        if text.is_empty() || parts.iter().any(|p| p.contains(&text)) {
            continue;
        }
        parts.push(text);
    }
    parts.join(": ")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn message_drops_repeats_and_cuts_long_tokens() {
        let os = std::io::Error::from(std::io::ErrorKind::NotFound);
        let inner = rgbid::io::IoError::file("a/b.txt", os);
        let e = anyhow::Error::new(inner).context("reading estimate");
        let m = message(&e);
        assert_eq!(m.matches("not found").count(), 1, "{m}");
        assert!(m.starts_with("reading estimate: a/b.txt: "), "{m}");

        let long = "x".repeat(10_000_000);
        let e = anyhow::anyhow!("bad token `{long}` at line 3");
        let m = message(&e);
        assert!(m.len() < 300, "{}", m.len());
        assert!(
            m.contains("(10000002 bytes)") && m.ends_with("at line 3"),
            "{m}"
        );

        let e = anyhow::anyhow!("unknown key `\u{feff}odometry`");
        assert!(message(&e).contains("<U+FEFF byte-order mark>odometry"));
    }

    #[test]
    fn exit_codes_by_ending() {
        assert_eq!(exit_code(&Warnings(vec!["x".into()]).into()), WARNINGS);
        let interrupted: anyhow::Error = Interrupted {
            out: Some("o".into()),
        }
        .into();
        assert_eq!(exit_code(&interrupted.context("slam")), INTERRUPTED);
        assert_eq!(exit_code(&anyhow::anyhow!("x")), ERROR);
        assert!(warnings(vec![]).is_ok());
    }
}
