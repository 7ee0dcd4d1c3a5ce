//! The viewer in a real X window: `rgbid-viewer` runs under Xvfb (on lavapipe in CI), a
//! screenshot of the X screen is taken with ImageMagick's `import`, and the regions of the
//! controls, image panels, 3D view and plots must hold drawn pixels. The frame-time line the
//! viewer prints (`RGBID_VIEWER_FRAME_BENCH`) is passed through.
//!
//! Needs `Xvfb` and `import` (`apt-get install xvfb imagemagick`; `.ci/run` installs them) and
//! a GPU adapter: `gpu_*`, ignored unless asked for; with `RGBID_REQUIRE_GPU=1` a missing
//! adapter or tool is a failure, otherwise the test prints `SKIPPED`.
//!
//! ```text
//! cargo test -p rgbid-viewer --test window -- --ignored --nocapture gpu_
//! cargo test -p rgbid-viewer --test window -- --ignored --nocapture manual_   # 250k / 1M points
//! ```

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

/// Size of the X screen; the viewer's window (1400x900) fills it from the top-left corner.
const SCREEN: (u32, u32) = (1400, 900);

/// Kills and reaps a child process when dropped.
struct Reaped(Child);

impl Drop for Reaped {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn tool(name: &str) -> Option<PathBuf> {
    let path = std::env::var_os("PATH")?;
    std::env::split_paths(&path)
        .map(|d| d.join(name))
        .find(|p| p.is_file())
}

/// Xvfb and import, or `None` after the skip-or-fail rule of GPU tests.
fn x_tools(test: &str) -> Option<(PathBuf, PathBuf)> {
    match (tool("Xvfb"), tool("import")) {
        (Some(x), Some(i)) => Some((x, i)),
        _ => {
            let why = "Xvfb or ImageMagick's import not found (apt-get install xvfb imagemagick)";
            if std::env::var(rgbid::gpu::REQUIRE_GPU_ENV).as_deref() == Ok("1") {
                panic!("{test}: {why}");
            }
            eprintln!("SKIPPED {test}: {why}");
            None
        }
    }
}

/// Starts Xvfb on a free display number; returns the process and `:N`.
fn start_xvfb(xvfb: &Path) -> (Reaped, String) {
    let base = 90 + (std::process::id() % 400);
    let n = (base..base + 100)
        .find(|n| {
            !Path::new(&format!("/tmp/.X11-unix/X{n}")).exists()
                && !Path::new(&format!("/tmp/.X{n}-lock")).exists()
        })
        .expect("a free X display number");
    let display = format!(":{n}");
    let child = Command::new(xvfb)
        .args([
            &display,
            "-screen",
            "0",
            &format!("{}x{}x24", SCREEN.0, SCREEN.1),
            "-nolisten",
            "tcp",
        ])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .expect("starting Xvfb");
    let socket = format!("/tmp/.X11-unix/X{n}");
    let t = Instant::now();
    while !Path::new(&socket).exists() {
        assert!(t.elapsed() < Duration::from_secs(20), "Xvfb did not start");
        std::thread::sleep(Duration::from_millis(100));
    }
    (Reaped(child), display)
}

/// Runs the viewer with `args` on `display` until it prints `ready` (after the run and the
/// frame-time measurement); returns the viewer (still showing its window) and its `ui frame`
/// line.
fn run_viewer(display: &str, args: &[&str], timeout: Duration) -> (Reaped, String) {
    let mut child = Command::new(env!("CARGO_BIN_EXE_rgbid-viewer"))
        .args(args)
        .env("DISPLAY", display)
        .env("RGBID_VIEWER_FRAME_BENCH", "30")
        .env(
            "XDG_RUNTIME_DIR",
            std::env::var_os("XDG_RUNTIME_DIR").unwrap_or_else(|| std::env::temp_dir().into()),
        )
        .env_remove("WAYLAND_DISPLAY")
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
        .expect("starting rgbid-viewer");
    let stdout = child.stdout.take().expect("piped stdout");
    let child = Reaped(child);
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(stdout).lines().map_while(Result::ok) {
            if tx.send(line).is_err() {
                break;
            }
        }
    });
    let t = Instant::now();
    let mut frame_line = String::new();
    loop {
        let left = timeout.saturating_sub(t.elapsed());
        match rx.recv_timeout(left) {
            Ok(l) if l == "ready" => break,
            Ok(l) if l.starts_with("ui frame") => frame_line = l,
            Ok(_) => {}
            Err(e) => panic!("rgbid-viewer {args:?}: no 'ready' line ({e:?}) within {timeout:?}"),
        }
    }
    (child, frame_line)
}

/// Takes a screenshot of the whole X screen.
fn screenshot(import: &Path, display: &str, out: &Path) -> image::RgbImage {
    let status = Command::new(import)
        .args(["-display", display, "-window", "root"])
        .arg(out)
        .status()
        .expect("running import");
    assert!(status.success(), "import failed: {status}");
    image::open(out).expect("reading the screenshot").to_rgb8()
}

/// Fraction of the pixels of `rect` (x0, y0, x1, y1) that differ from the region's most
/// common colour (its background) by more than 24 in some channel, and that colour.
fn drawn_fraction(img: &image::RgbImage, (x0, y0, x1, y1): (u32, u32, u32, u32)) -> (f64, [u8; 3]) {
    let mut counts = std::collections::HashMap::new();
    for y in y0..y1 {
        for x in x0..x1 {
            *counts.entry(img.get_pixel(x, y).0).or_insert(0usize) += 1;
        }
    }
    let bg = counts
        .iter()
        .max_by_key(|(_, n)| **n)
        .map(|(c, _)| *c)
        .unwrap_or_default();
    let differs = |p: [u8; 3]| (0..3).any(|k| p[k].abs_diff(bg[k]) > 24);
    let n: usize = counts
        .iter()
        .filter(|(c, _)| differs(**c))
        .map(|(_, n)| n)
        .sum();
    (n as f64 / f64::from((x1 - x0) * (y1 - y0)), bg)
}

#[test]
#[ignore = "needs a GPU adapter"]
fn gpu_window_under_xvfb_draws_all_panels() {
    let test = "gpu_window_under_xvfb_draws_all_panels";
    if rgbid::gpu::test_gpu(test).is_none() {
        return;
    }
    let Some((xvfb, import)) = x_tools(test) else {
        return;
    };
    let (_x, display) = start_xvfb(&xvfb);
    let (_viewer, frame_line) = run_viewer(
        &display,
        &[
            "--synth",
            "office:loop",
            // A third of the loop in 90 frames: the per-frame motion of the demo's
            // 390 frames over 1.3 laps, so every frame tracks and keyframes add points.
            "--frames",
            "90",
            "--laps",
            "0.3",
            "--width",
            "160",
            "--backend",
            "cpu",
        ],
        Duration::from_secs(600),
    );
    println!("{frame_line}");
    let out = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("viewer-window.png");
    let img = screenshot(&import, &display, &out);
    println!("screenshot: {}", out.display());
    assert_eq!(img.dimensions(), SCREEN);
    // The layout of the 1400x900 window: controls on top, image panels on the left (340
    // points), plots at the bottom (230 points), the 3D view in the middle.
    let regions = [
        ("controls", (0, 0, 900, 60), 0.02),
        ("image panels", (0, 80, 320, 600), 0.15),
        ("3D view", (350, 110, 1390, 650), 0.01),
        ("plots", (350, 720, 1390, 890), 0.02),
    ];
    for (name, rect, least) in regions {
        let (f, bg) = drawn_fraction(&img, rect);
        println!("{name}: {:.1} % drawn (background {bg:?})", 100.0 * f);
        assert!(
            f >= least,
            "{name}: only {:.2} % of {rect:?} differs from its background {bg:?} (screenshot {})",
            100.0 * f,
            out.display()
        );
    }
    // The 3D view's own clear colour (0.07, 0.07, 0.09) is its background: the wgpu paint
    // callback ran in the window.
    let (_, bg) = drawn_fraction(&img, regions[2].1);
    assert!(
        bg[2] > bg[0] && bg[0] < 30,
        "3D view background {bg:?} is not the scene's clear colour"
    );
}

/// UI frame time in the window with the point cloud of a generated run plus synthetic points
/// (250k and 1M in all), printed; not checked (it depends on the machine).
#[test]
#[ignore = "benchmark: prints the UI frame time in an Xvfb window"]
fn manual_window_frame_time() {
    let test = "manual_window_frame_time";
    let Some((xvfb, import)) = x_tools(test) else {
        return;
    };
    let (_x, display) = start_xvfb(&xvfb);
    for points in ["250000", "1000000"] {
        let (_viewer, frame_line) = run_viewer(
            &display,
            &["--bench-points", points],
            Duration::from_secs(300),
        );
        println!("{frame_line}");
        let out =
            PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join(format!("viewer-window-{points}.png"));
        screenshot(&import, &display, &out);
        println!("screenshot: {}", out.display());
    }
}
