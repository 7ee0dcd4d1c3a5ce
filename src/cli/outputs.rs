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
                eprintln!(
                    "\nsecond interrupt: exiting now; the outputs are those of the last \
                     checkpoint"
                );
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
/// per-frame files are flushed frame by frame, and the trajectories are those of the last
/// checkpoint).
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

/// Default seconds of input (frame time stamps) between two checkpoints.
pub const CHECKPOINT_EVERY_S: f64 = 5.0;

/// When checkpoints are due: every `every_s` seconds of input, by the frames' time stamps
/// (not wall time, so that a slow machine and a fast one checkpoint the same frames).
pub struct Checkpoints {
    every_s: f64,
    next: Option<f64>,
}

impl Checkpoints {
    /// A clock that fires every `every_s` seconds of input (> 0, finite; see `range::positive`).
    pub fn new(every_s: f64) -> Self {
        Checkpoints {
            every_s,
            next: None,
        }
    }

    /// Whether a checkpoint is due after the frame stamped `timestamp` (seconds). The first
    /// frame starts the clock; time stamps that go back (a sequence that restarts its clock)
    /// start it again.
    pub fn due(&mut self, timestamp: f64) -> bool {
        match self.next {
            Some(next) if timestamp >= next => {
                self.next = Some(timestamp + self.every_s);
                true
            }
            Some(next) if timestamp >= next - self.every_s => false,
            _ => {
                self.next = Some(timestamp + self.every_s);
                false
            }
        }
    }
}

/// Skipped frames should be fewer than this, or at most half of the frames tried, for the run
/// to go on.
const MAX_SKIPPED: usize = 10;

/// Frames skipped because their images could not be used (corrupt or truncated files, a
/// wrong size, no valid depth, an implausible depth scale), and when to give up: one bad
/// frame is skipped and counted, but when most frames fail the input's settings are wrong and
/// the error (with its advice) stops the run.
#[derive(Default)]
pub struct Skips {
    /// Frames skipped so far.
    pub count: usize,
    /// The first skipped frame's error, as printed.
    first: Option<String>,
}

impl Skips {
    /// Counts frame `index` (0-based) as skipped because of `error`, and logs it. Returns
    /// the error that stops the run when skipped frames are most of those tried.
    pub fn skip(&mut self, index: usize, error: anyhow::Error) -> Option<anyhow::Error> {
        let e = error.context(format!("frame {index}"));
        let text = super::outcome::message(&e);
        log::warn!("skipping {text}");
        self.count += 1;
        self.first.get_or_insert(text);
        if self.count >= MAX_SKIPPED && 2 * self.count > index + 1 {
            return Some(e.context(format!(
                "{} of the first {} frames could not be used",
                self.count,
                index + 1
            )));
        }
        None
    }

    /// The warning of a run that skipped frames (exit code 3), if it did.
    pub fn warning(&self) -> Option<String> {
        self.first.as_ref().map(|first| {
            format!(
                "{} frames skipped (no pose for them), the first: {first}",
                self.count
            )
        })
    }
}

/// Whether a frame's load error concerns that frame's content alone (a corrupt, truncated or
/// wrongly sized image, no valid depth, an implausible depth scale) rather than the sequence
/// or its settings; such a frame is skipped (see [`Skips`]).
pub fn frame_content_error(e: &rgbid::io::IoError) -> bool {
    use rgbid::io::IoError;
    matches!(
        e,
        IoError::Image { .. }
            | IoError::DepthScaleMismatch { .. }
            | IoError::DepthNot16Bit { .. }
            | IoError::NoValidDepth { .. }
            | IoError::ImageSizeMismatch { .. }
            | IoError::CameraSizeMismatch { .. }
            | IoError::Frame { .. }
    )
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

    #[test]
    fn checkpoints_every_few_seconds_of_input() {
        let mut c = Checkpoints::new(1.0);
        let fired: Vec<bool> = [10.0, 10.5, 10.99, 11.0, 11.5, 12.1, 12.2]
            .into_iter()
            .map(|t| c.due(t))
            .collect();
        assert_eq!(fired, [false, false, false, true, false, true, false]);
        // A clock that goes back starts again.
        assert!(!c.due(0.0));
        assert!(!c.due(0.9));
        assert!(c.due(1.0));
    }

    #[test]
    fn one_bad_frame_is_skipped_but_most_frames_bad_stop_the_run() {
        let mut s = Skips::default();
        assert!(s.skip(5, anyhow::anyhow!("bad png")).is_none());
        let w = s.warning().expect("a warning");
        assert!(
            w.starts_with("1 frames skipped") && w.contains("frame 5: bad png"),
            "{w}"
        );
        let mut s = Skips::default();
        let stop = (0..20).find_map(|i| s.skip(i, anyhow::anyhow!("depth factor")));
        let e = format!("{:#}", stop.expect("stops"));
        assert!(e.contains("10 of the first 10 frames"), "{e}");
        assert!(e.contains("depth factor"), "{e}");
    }
}
