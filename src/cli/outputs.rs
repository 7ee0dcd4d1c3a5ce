//! Output locations checked before the work starts, and the SIGINT/SIGTERM handling of the
//! long-running commands.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;

use anyhow::{bail, Context, Result};

/// The folder a path would be created in (`.` for a bare file name).
fn parent_of(path: &Path) -> &Path {
    match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    }
}

/// Creates `dir` (and its parents) and checks that a file can be created in it.
fn writable_folder(dir: &Path) -> Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    tempfile::Builder::new()
        .prefix(".rgbid-probe-")
        .tempfile_in(dir)
        .with_context(|| format!("{} is not writable", dir.display()))?;
    Ok(())
}

/// Whether two paths name the same existing file or folder.
fn same(a: &Path, b: &Path) -> bool {
    match (a.canonicalize(), b.canonicalize()) {
        (Ok(a), Ok(b)) => a == b,
        _ => false,
    }
}

/// Checks an output file before the work: its folder is created and writable, it is not a
/// folder, and it is none of `inputs`.
pub fn output_file(path: &Path, what: &str, inputs: &[&Path]) -> Result<()> {
    if path.is_dir() {
        bail!("{what} {} is a folder; give a file name", path.display());
    }
    for input in inputs {
        if same(path, input) {
            bail!(
                "{what} {} is also an input; choose another output file",
                path.display()
            );
        }
    }
    writable_folder(parent_of(path)).with_context(|| format!("{what} {}", path.display()))
}

/// Checks an output folder before the work: created, writable, and not the input folder
/// (whose files, `groundtruth.txt` among them, a run folder would replace).
pub fn output_folder(dir: &Path, input: Option<&Path>) -> Result<()> {
    if dir.exists() && !dir.is_dir() {
        bail!("output folder {} is a file", dir.display());
    }
    if let Some(input) = input {
        if same(dir, input) {
            bail!(
                "output folder {} is the input sequence folder; its files would be replaced: \
                 choose another --out",
                dir.display()
            );
        }
    }
    writable_folder(dir).with_context(|| format!("output folder {}", dir.display()))
}

/// SIGINT/SIGTERM: the first asks the run to stop reading frames and write everything; the
/// second exits at once (exit code 130) with what the last checkpoint wrote.
#[derive(Clone)]
pub struct Stop {
    signals: Arc<AtomicUsize>,
}

impl Stop {
    /// Installs the handler. `on_second` runs on the second signal, right before the exit
    /// (marking the outputs as interrupted).
    pub fn install(on_second: impl Fn() + Send + 'static) -> Result<Self> {
        let signals = Arc::new(AtomicUsize::new(0));
        let seen = signals.clone();
        ctrlc::set_handler(move || {
            if seen.fetch_add(1, Ordering::SeqCst) == 0 {
                eprintln!(
                    "\nstopping: finishing the frames read so far and writing the outputs \
                     (a second Ctrl-C exits at once)"
                );
            } else {
                on_second();
                std::process::exit(super::outcome::INTERRUPTED);
            }
        })
        .context("cannot install the SIGINT/SIGTERM handler")?;
        Ok(Stop { signals })
    }

    /// Whether a stop was asked for.
    pub fn requested(&self) -> bool {
        self.signals.load(Ordering::SeqCst) > 0
    }
}

/// Marks the run folder's `summary.json` as interrupted (the second signal's last act; the
/// per-frame files are flushed frame by frame and need nothing).
pub fn mark_interrupted(dir: &Path) {
    let path: PathBuf = dir.join(rgbid::io::run_folder::files::SUMMARY);
    let Ok(text) = std::fs::read_to_string(&path) else {
        return;
    };
    let Ok(mut value) = serde_json::from_str::<serde_json::Value>(&text) else {
        return;
    };
    if let Some(map) = value.as_object_mut() {
        map.insert(
            "status".into(),
            rgbid::io::run_folder::STATUS_INTERRUPTED.into(),
        );
        map.insert("complete".into(), false.into());
    }
    let Ok(text) = serde_json::to_string_pretty(&value) else {
        return;
    };
    if let Ok(mut tmp) = tempfile::NamedTempFile::new_in(dir) {
        use std::io::Write;
        if tmp.write_all(text.as_bytes()).is_ok() {
            let _ = tmp.persist(&path);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn outputs_are_checked_before_the_work() {
        let d = tempfile::tempdir().unwrap();
        let seq = d.path().join("seq");
        std::fs::create_dir(&seq).unwrap();
        let e = output_folder(&seq, Some(&seq)).unwrap_err().to_string();
        assert!(e.contains("is the input sequence folder"), "{e}");
        // Parents are created.
        let deep = d.path().join("a/b/c");
        output_folder(&deep, Some(&seq)).unwrap();
        assert!(deep.is_dir());
        output_file(&d.path().join("x/y/t.txt"), "--out", &[]).unwrap();
        assert!(d.path().join("x/y").is_dir());
        let gt = seq.join("groundtruth.txt");
        std::fs::write(&gt, "# gt\n").unwrap();
        let e = output_file(&gt, "--out", &[&gt]).unwrap_err().to_string();
        assert!(e.contains("is also an input"), "{e}");
        let e = format!("{:#}", output_file(&seq, "--out", &[]).unwrap_err());
        assert!(e.contains("is a folder"), "{e}");
    }
}
