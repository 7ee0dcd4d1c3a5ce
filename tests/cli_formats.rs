//! Trajectory formats on the command line: `rgbid odometry --out` writes TUM, KITTI and EuRoC
//! files of the same run, and `rgbid eval` reads each (detected) to the same figures.

use std::path::Path;

#[path = "common/cli.rs"]
mod cli;
use cli::{rgbid, text};

fn path(p: &Path) -> &str {
    p.to_str().expect("utf-8 path")
}

/// `rgbid eval --json` of `est` against `gt`: (ATE RMSE m, RPE translation RMSE m, matched).
fn eval(gt: &Path, est: &Path, extra: &[&str]) -> (f64, f64, u64) {
    let mut args = vec!["eval", path(gt), path(est), "--json"];
    args.extend_from_slice(extra);
    let o = rgbid(&args);
    assert!(o.status.success(), "{}", text(&o));
    let m: serde_json::Value = serde_json::from_slice(&o.stdout).expect("json");
    (
        m["ate"]["translation"]["rmse"].as_f64().expect("ate"),
        m["rpe_frame"]["translation_m"]["rmse"]
            .as_f64()
            .expect("rpe"),
        m["matched"].as_u64().expect("matched"),
    )
}

#[test]
fn odometry_writes_each_format_and_eval_reads_them_alike() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let seq = tmp.path().join("seq");
    let o = rgbid(&[
        "synth",
        "--frames",
        "8",
        "--width",
        "160",
        "--backend",
        "cpu",
        "--out",
        path(&seq),
    ]);
    assert!(o.status.success(), "{}", text(&o));
    let gt = seq.join("groundtruth.txt");
    let mut figures = Vec::new();
    for name in ["t.txt", "t.kitti", "t.csv"] {
        let out = tmp.path().join(name);
        let o = rgbid(&[
            "odometry",
            path(&seq),
            "--backend",
            "cpu",
            "--out",
            path(&out),
        ]);
        assert!(o.status.success(), "{name}: {}", text(&o));
        figures.push((name, eval(&gt, &out, &[])));
    }
    assert!(tmp.path().join("t.times.txt").is_file());
    assert!(std::fs::read_to_string(tmp.path().join("t.csv"))
        .expect("csv")
        .starts_with("#timestamp [ns]"));
    let (_, (ate, rpe, matched)) = figures[0];
    assert_eq!(matched, 8);
    assert!(ate < 0.02, "ATE {ate}");
    for (name, (a, r, m)) in &figures[1..] {
        assert_eq!(*m, matched, "{name}");
        assert!(
            (a - ate).abs() < 1e-5 && (r - rpe).abs() < 1e-5,
            "{name}: {a} {r} vs {ate} {rpe}"
        );
    }
    // A clock offset larger than the matching window leaves nothing to match.
    let o = rgbid(&[
        "eval",
        path(&gt),
        path(&tmp.path().join("t.csv")),
        "--t-offset",
        "-5",
    ]);
    assert!(!o.status.success());
}

/// Writes a TUM trajectory of `n` poses on a circle of radius 1 m in the x-z plane at 10 Hz,
/// with `offset` added to x.
fn circle(path: &Path, n: usize, offset: f64) {
    let lines: Vec<String> = (0..n)
        .map(|i| {
            let a = i as f64 / n as f64 * std::f64::consts::TAU;
            let x = a.cos() + offset * (i as f64 / n as f64);
            format!("{:.3} {x:.6} 0.1 {:.6} 0 0 0 1", 0.1 * i as f64, a.sin())
        })
        .collect();
    std::fs::write(path, lines.join("\n") + "\n").expect("write trajectory");
}

#[test]
fn eval_plots_top_view_and_error_over_time() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let (gt, est, png) = (
        tmp.path().join("gt.txt"),
        tmp.path().join("est.txt"),
        tmp.path().join("plot.png"),
    );
    circle(&gt, 60, 0.0);
    circle(&est, 60, 0.2);
    let o = rgbid(&["eval", path(&gt), path(&est), "--plot", path(&png)]);
    assert!(o.status.success(), "{}", text(&o));
    let img = image::open(&png).expect("plot is a PNG").to_rgb8();
    assert_eq!(img.dimensions(), (1600, 700));
    let count = |c: [u8; 3]| img.pixels().filter(|p| p.0 == c).count();
    // Both trajectories and the error curve are drawn in their colours, and text is there.
    let (blue, dark) = (count([30, 80, 200]), count([40, 40, 40]));
    assert!(blue > 500 && dark > 300, "blue {blue} dark {dark}");
    let white = count([255, 255, 255]);
    assert!(white < 1600 * 700 * 98 / 100, "the plot is almost empty");

    // Without a font the error says how to get one, and no plot is written.
    let png2 = tmp.path().join("plot2.png");
    let o = std::process::Command::new(env!("CARGO_BIN_EXE_rgbid"))
        .args(["eval", path(&gt), path(&est), "--plot", path(&png2)])
        .env("RGBID_FONT", tmp.path().join("no-such-font.ttf"))
        .output()
        .expect("running rgbid");
    assert!(!o.status.success());
    let t = text(&o);
    assert!(
        t.contains("no-such-font.ttf") && t.contains("RGBID_FONT"),
        "{t}"
    );
    assert!(!png2.exists());
}
